"""An opt-in memory probe for the service child of the soaks (off unless RSSDIAG_DIR is set; never imported by the
package). How the soak's RSS creep was traced to glibc's heaps (docs/tracking.md, docs/history.md):

    RSSDIAG_DIR=out/probe PYTHONPATH=benchmarks/rss_probe \
        python benchmarks/track_soak.py --seconds 660 --kill-at 0.95 --cache out/cars

Python imports this file as ``sitecustomize`` in every process; only a ``python -c`` child (the service the
harness starts) runs the probe thread. Every 15 s it appends to RSSDIAG_DIR/diag-<pid>.jsonl: RSS, anonymous and
file memory (smaps_rollup), threads, mappings, and glibc's mallinfo2 (arena: heap bytes; uordblks: handed out;
fordblks: free but kept; hblkhd: blocks mapped on their own). Optional, seconds since the child started:
RSSDIAG_TM_START (tracemalloc from then; RSSDIAG_DEPTH frames), RSSDIAG_SNAPS=200,560 (tracemalloc snapshots,
compare with tmdiff.py), RSSDIAG_GC=200,560 (object counts by type), RSSDIAG_TRIMS=480,600 or
RSSDIAG_TRIM_EVERY=60 (malloc_trim(0), RSS before and after).
"""

import os
import sys
import threading
import time


def _diag():
    time.sleep(2.0)
    if sys.argv[:1] != ["-c"]:
        return
    import ctypes
    import gc
    import json
    import tracemalloc
    from collections import Counter

    out = os.environ["RSSDIAG_DIR"]
    pid = os.getpid()
    t0 = time.time()
    tm_start = float(os.environ.get("RSSDIAG_TM_START", "-1"))
    snaps = [float(x) for x in os.environ.get("RSSDIAG_SNAPS", "").split(",") if x]
    trims = [float(x) for x in os.environ.get("RSSDIAG_TRIMS", "").split(",") if x]
    gcs = [float(x) for x in os.environ.get("RSSDIAG_GC", "").split(",") if x]
    trim_every = float(os.environ.get("RSSDIAG_TRIM_EVERY", "0"))
    libc = ctypes.CDLL("libc.so.6")

    class MI2(ctypes.Structure):
        _fields_ = [
            (n, ctypes.c_size_t)
            for n in (
                "arena",
                "ordblks",
                "smblks",
                "hblks",
                "hblkhd",
                "usmblks",
                "fsmblks",
                "uordblks",
                "fordblks",
                "keepcost",
            )
        ]

    libc.mallinfo2.restype = MI2

    def rss():
        d = {}
        for line in open(f"/proc/{pid}/smaps_rollup"):
            k, _, v = line.partition(":")
            if k in ("Rss", "Anonymous", "Pss_File", "Pss_Anon"):
                d[k] = int(v.split()[0]) / 1024
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("Threads:"):
                d["threads"] = int(line.split()[1])
        d["maps"] = sum(1 for _ in open(f"/proc/{pid}/maps"))
        mi = libc.mallinfo2()
        d.update({k: getattr(mi, k) / 2**20 for k in ("arena", "hblkhd", "uordblks", "fordblks", "keepcost")})
        d["hblks"] = mi.hblks
        return d

    fh = open(f"{out}/diag-{pid}.jsonl", "a", buffering=1)
    last_trim = 0.0
    while True:
        t = time.time() - t0
        rec = {"t": round(t, 1), **rss()}
        if tm_start >= 0 and t >= tm_start and not tracemalloc.is_tracing():
            tracemalloc.start(int(os.environ.get("RSSDIAG_DEPTH", "12")))
            rec["tm_started"] = True
        if tracemalloc.is_tracing():
            rec["tm_cur"] = tracemalloc.get_traced_memory()[0] / 2**20
            rec["tm_overhead"] = tracemalloc.get_tracemalloc_memory() / 2**20
        if snaps and t >= snaps[0] and tracemalloc.is_tracing():
            s = snaps.pop(0)
            tracemalloc.take_snapshot().dump(f"{out}/snap-{pid}-{int(s)}.pkl")
            rec["snap"] = s
        if gcs and t >= gcs[0]:
            s = gcs.pop(0)
            c = Counter(type(o).__qualname__ for o in gc.get_objects())
            json.dump(dict(c.most_common(300)), open(f"{out}/gc-{pid}-{int(s)}.json", "w"))
            rec["gc"] = s
        if (trims and t >= trims[0]) or (trim_every and t - last_trim >= trim_every):
            if trims and t >= trims[0]:
                trims.pop(0)
            last_trim = t
            before = rss()["Rss"]
            libc.malloc_trim(0)
            rec["trim"] = [before, rss()["Rss"]]
        fh.write(json.dumps(rec) + "\n")
        time.sleep(15.0)


if os.environ.get("RSSDIAG_DIR"):
    threading.Thread(target=_diag, name="rssdiag", daemon=True).start()
