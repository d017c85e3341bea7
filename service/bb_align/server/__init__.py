"""The ego-side service: Zenoh and REST doors, ego-frame cache, latest-only queues, worker pool, metrics.

    from bb_align.server import create_app
    app = create_app(Settings(ego_id="car0"))   # FastAPI app; its lifespan runs the workers and the Zenoh link

Imports are lazy so that ``bb-align --help`` does not load FastAPI or Zenoh.
"""

from __future__ import annotations

__all__ = ["AlignService", "create_app"]


def __getattr__(name: str):
    if name == "create_app":
        from bb_align.server.app import create_app

        return create_app
    if name == "AlignService":
        from bb_align.server.core import AlignService

        return AlignService
    raise AttributeError(name)
