"""Defaults shared by the commands that read a dataset (``recover``, ``eval``, ``track``). Free of imports, so that
the CLI can name them in its options without loading numpy.

``DESKEW_DEFAULT``: the one de-skew default (``--deskew/--no-deskew`` on each command, ``deskew`` in their configs):
the same data gives the same answer whichever command reads it. The service de-skews nothing itself: its senders
do (``bb_align_client.encode_frame(velocity=...)``, ``deskew_sweep``)."""

DESKEW_DEFAULT = True
DESKEW_HELP = (
    "de-skew each cloud whose yaml carries its sweep's motion ('sweep_twist': the simulator's sweeps rendered with "
    "self-motion distortion), as a sender with odometry does before it encodes; its boxes move with it"
)
