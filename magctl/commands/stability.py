"""``magctl stability servo|front|side``: loop analyses under one command.

``servo`` comes from :mod:`magctl.commands.stability_servo`; ``front`` and
``side`` are added by :func:`magctl.stability.register_front` and
:func:`magctl.stability.register_side` when that module is present.
"""

from __future__ import annotations

from magctl.commands.stability_servo import register_servo


def register(sub) -> None:
    p = sub.add_parser("stability", help="stability analysis of the servo and push loops")
    inner = p.add_subparsers(dest="loop", metavar="LOOP")
    inner.required = True
    register_servo(inner)
    try:
        from magctl import stability
    except ImportError:
        return
    for hook in ("register_front", "register_side"):
        fn = getattr(stability, hook, None)
        if fn is not None:
            fn(inner)
