"""Write ``openapi.json`` (project root) from the app: ``python -m service.openapi [--check]``.

``--check`` only compares and exits 1 if the file is out of date (a test does the same).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

OPENAPI_PATH = Path(__file__).resolve().parents[1] / "openapi.json"


def openapi_schema() -> dict[str, Any]:
    from service.main import create_app

    return create_app().openapi()


def render(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.openapi", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if openapi.json is out of date")
    parser.add_argument("--out", type=Path, default=OPENAPI_PATH)
    args = parser.parse_args(argv)
    text = render(openapi_schema())
    if args.check:
        ok = args.out.is_file() and args.out.read_text() == text
        print(f"{args.out}: {'up to date' if ok else 'OUT OF DATE: run python -m service.openapi'}")
        return 0 if ok else 1
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
