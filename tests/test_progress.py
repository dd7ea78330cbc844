"""Progress bars (`neuralrt.progress`): redrawn every LOG_REDRAW_SECONDS into a log, as often as
tqdm likes on a terminal."""

import io
import os
import subprocess
import sys

import pytest

from neuralrt import api
from neuralrt.progress import LOG_REDRAW_SECONDS, progress_bar


class _Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.skipif("TQDM_MININTERVAL" in os.environ, reason="tqdm read TQDM_MININTERVAL when imported")
@pytest.mark.parametrize("stream, interval", [(io.StringIO(), LOG_REDRAW_SECONDS), (_Terminal(), 0.1)])
def test_a_log_gets_fewer_redraws_than_a_terminal(stream, interval, monkeypatch):
    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    with progress_bar(total=3, file=stream) as bar:
        assert bar.mininterval == interval and bar.maxinterval == max(interval, 10)  # (tqdm's own: 10 s)


def test_tqdms_own_setting_wins():
    # (tqdm reads TQDM_* when it is imported: a process of its own)
    code = "import io; from neuralrt.progress import progress_bar; print(progress_bar(total=1, file=io.StringIO()).mininterval)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "TQDM_MININTERVAL": "2"})
    assert done.stdout.strip() == "2.0", done.stderr


def test_a_training_into_a_log_draws_its_start_and_end(tmp_path, capsys, monkeypatch):
    # (a 200-step training wrote a redraw every ~0.1 s, each with its figures, joined by carriage returns)
    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    api.train("procedural:statue:0", tmp_path / "m.nrt", steps=60, batch=1024, progress=True)
    err = capsys.readouterr().err
    assert err.count("\r") <= 3 and "60/60" in err and "loss=" in err  # (the last redraw has the figures)


def test_a_new_postfix_redraws_a_terminal_at_once_and_a_log_after_its_interval(monkeypatch):
    from neuralrt.progress import redraw_due

    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    with progress_bar(total=3, file=_Terminal()) as bar:
        bar.last_print_t -= 0.2
        assert redraw_due(bar)
    with progress_bar(total=3, file=io.StringIO()) as bar:
        assert not redraw_due(bar)
        bar.last_print_t -= LOG_REDRAW_SECONDS
        assert redraw_due(bar)
