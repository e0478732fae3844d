"""Seeing a run: the live page of a running task and the replay page of run logs (docs/rig.md "Live view").

* :mod:`magctl.view.scene` — what the page draws, from a run's own documents;
* :mod:`magctl.view.feed` — the runtime's monitor: the latest frame, never waited on;
* :mod:`magctl.view.replay` — run logs indexed for the replay page;
* :mod:`magctl.view.server` — the starlette/uvicorn server of both pages (the ``view`` extra).
"""
