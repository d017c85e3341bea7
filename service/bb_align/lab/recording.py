"""Where a benchmark writes: ``out/`` unless asked to record (``--record``, ``make ... RECORD=1``), so that running
one leaves the checkout as it was; the recorded output the docs cite lives under ``docs/``."""

from __future__ import annotations

from pathlib import Path

RECORD_HELP = "write into docs/ (the recorded output the docs cite); default: the same path under out/"


def output_path(docs_path: str | Path, record: bool = False) -> Path:
    """``docs_path`` (``docs/...``) when recording, else the same path under ``out/``."""
    docs_path = Path(docs_path)
    return docs_path if record else Path("out") / docs_path.relative_to("docs")
