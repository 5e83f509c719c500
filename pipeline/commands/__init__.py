"""CLI sub-commands: one module per command group, each with ``register(subparsers)``.

:mod:`pipeline.cli` discovers the modules of this package; a module's
``register`` adds its parser(s) and sets ``func`` to a callable taking the
parsed ``argparse.Namespace`` and returning an exit code. Modules whose names start
with ``_`` are helpers shared by the commands, not commands.
"""

import json
import math


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return "inf" if value > 0 else "-inf" if value < 0 else "nan"
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item) for item in value]
    return value


def print_json(obj) -> None:
    """Print strict JSON (infinities as the strings "inf"/"-inf")."""
    print(json.dumps(_json_safe(obj), indent=2, default=str))
