"""Compare two tracemalloc snapshots of the probe (sitecustomize.py): what grew, by line and by traceback.

python benchmarks/rss_probe/tmdiff.py out/probe/snap-<pid>-200.pkl out/probe/snap-<pid>-560.pkl
"""

import sys
import tracemalloc

a, b = (tracemalloc.Snapshot.load(p) for p in sys.argv[1:3])
filt = [tracemalloc.Filter(False, tracemalloc.__file__)]
a, b = a.filter_traces(filt), b.filter_traces(filt)
total = [sum(s.size for s in snap.statistics("filename")) / 2**20 for snap in (a, b)]
print(f"traced: {total[0]:.1f} MB -> {total[1]:.1f} MB")
for key, n in (("lineno", 12), ("traceback", 5)):
    print("== by", key)
    for s in b.compare_to(a, key)[:n]:
        print(f"{s.size_diff / 2**20:+.2f} MB ({s.count_diff:+d} blocks), now {s.size / 2**20:.2f} MB")
        for line in s.traceback.format()[-12:] if key == "traceback" else [str(s.traceback[0])]:
            print("     ", line)
