"""Write docs/operations.md, the reference of every ``procam`` command, from the command's own parser.

    python scripts/gen_ops_reference.py           # write the page
    python scripts/gen_ops_reference.py --check   # exit 1 when the committed page differs from the parser

Run it after changing a command's options; ``tests/test_docs.py`` fails until the page is written again.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from procam.addon.cli.reference import render

PAGE = Path(__file__).resolve().parents[1] / "docs" / "operations.md"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing; exit 1 when they differ")
    args = parser.parse_args()
    text = render()
    if args.check:
        same = PAGE.is_file() and PAGE.read_text(encoding="utf-8") == text
        print(f"{PAGE}: {'up to date' if same else 'differs from the parser: run scripts/gen_ops_reference.py'}")
        return 0 if same else 1
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
