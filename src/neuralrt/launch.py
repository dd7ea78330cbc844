"""The `neuralrt` command's entry point: the CLI (and torch, ~1 s to import) is imported here, so a
Ctrl-C during that import is the CLI's one line too, not a traceback from inside torch."""

import sys


def main() -> int:
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:
        print("neuralrt: interrupted", file=sys.stderr)
        return 130
    return cli_main()
