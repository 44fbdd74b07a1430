"""`stgc` command line. Verbs and their options are generated from the config dataclasses."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    print("stgc: work in progress", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
