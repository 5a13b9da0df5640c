"""The tail every benchmark script shares: print its report and, if asked, write its record as JSON."""

from __future__ import annotations

import json


def emit(record: dict, text: str, json_path: str | None) -> None:
    """Print ``text``; write ``record`` to ``json_path`` (indented JSON) unless it is None."""
    print(text)
    if json_path:
        with open(json_path, "w") as f:
            json.dump(record, f, indent=2)
