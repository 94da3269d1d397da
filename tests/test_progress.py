"""Progress fit for logs: a few lines where stderr is not a terminal (issue #21)."""

import io

from cohflash_jax.progress import LogProgress, progress_bar


def test_a_log_gets_a_line_per_tenth_not_per_update():
    log = io.StringIO()
    with LogProgress(total=81920, desc="reconstruct", unit="px", file=log) as bar:
        for _ in range(640):  # 640 chunks of 128 px
            bar.update(128)
    lines = log.getvalue().splitlines()
    assert len(lines) == 10, lines
    assert "\r" not in log.getvalue()
    assert lines[0].startswith("reconstruct: 10% (8192/81920 px)")
    assert lines[-1].startswith("reconstruct: 100% (81920/81920 px)")


def test_iteration_resumed_work_and_no_total():
    log = io.StringIO()
    items = list(LogProgress(range(3), desc="posterior", unit="px", file=log))
    assert items == [0, 1, 2]
    assert log.getvalue().splitlines()[-1].startswith("posterior: 100% (3/3 px)")
    log = io.StringIO()
    with LogProgress(total=100, initial=95, desc="sweep", unit="pt", file=log) as bar:
        bar.update(5)  # a resumed sweep: one line, at the end
    assert log.getvalue().splitlines() == [log.getvalue().splitlines()[0]]
    log = io.StringIO()
    with LogProgress(desc="x", file=log) as bar:
        bar.update(3)
    assert log.getvalue().startswith("x: 3 it")
    log = io.StringIO()
    with LogProgress(total=10, desc="quiet", disable=True, file=log) as bar:
        bar.update(10)
    assert log.getvalue() == ""


def test_a_stderr_that_is_not_a_terminal_gets_the_log_form(monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert isinstance(progress_bar(total=3, desc="t", disable=True), LogProgress)
