"""Reading the JSON documents slamtka exchanges (plans, cases, calibrations, contours, status).

Every such file holds one JSON object; whatever is wrong with it (missing, unreadable, not
text, not JSON, not an object) is refused with the file named, so a user sees which of the
many files of a case or plan to fix.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["read_json_object"]


def read_json_object(path: str | Path) -> dict:
    """The JSON object in ``path``; ValueError naming the file and the problem otherwise."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file missing")
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8) file") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: must hold a JSON object, not {type(doc).__name__}")
    return doc
