"""The `neuralrt` command's entry point: the CLI (and torch, ~1 s to import) is imported here, so a
Ctrl-C during that import is the CLI's one line too, not a traceback from inside torch."""

import signal
import sys


def main() -> int:
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:
        print("neuralrt: interrupted", file=sys.stderr)
        return 130
    ignored = [s for s in (signal.SIGINT, signal.SIGTERM) if signal.getsignal(s) is signal.SIG_IGN]  # (as inherited)
    code = cli_main()
    _signals_end_the_process(ignored)
    return code


def _signals_end_the_process(ignored: list) -> None:
    """After the command, its result printed: a Ctrl-C or SIGTERM during the interpreter's shutdown
    ends the process as the signal does by default. Python's handler raised KeyboardInterrupt inside
    whichever exit callback was running (tqdm's, numba's) and printed its traceback. The outputs are
    in place by then (renamed into place; Ray shut down); exit callbacks not yet run are skipped (a
    per-process numba cache folder in the temporary folder can stay). A signal the process was
    started ignoring (``nohup``, a background job of a script) stays ignored."""
    from .cli import discard_the_rest  # (imported already: main ran it)

    for stream in (sys.stdout, sys.stderr):
        if stream is None:  # (started with it closed: `>&-`)
            continue
        try:
            stream.flush()  # (what the command printed is out before the process can end)
        except (OSError, ValueError):  # (already reported by the command, or a closed pipe)
            discard_the_rest(stream)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN if sig in ignored else signal.SIG_DFL)
