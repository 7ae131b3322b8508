"""Progress (`posegrasp.core.progress`): a bar on a terminal, a few plain lines in a log."""

from __future__ import annotations

import io

from posegrasp.core.backends import run_map
from posegrasp.core.progress import progress_bar


class Terminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def _square(x: int) -> int:
    return x * x


def test_a_log_gets_a_line_per_tenth_and_no_carriage_returns() -> None:
    log = io.StringIO()
    assert sum(progress_bar(range(1000), desc="episodes", stream=log)) == sum(range(1000))
    text = log.getvalue()
    lines = text.splitlines()
    assert "\r" not in text
    assert len(lines) == 10  # 10 %, 20 %, ..., 90 % and the last line
    assert lines[0].startswith("episodes 100/1000 (10 %), ")
    assert lines[-1].startswith("episodes 1000/1000 (100 %), ")


def test_a_counted_bar_without_a_total_writes_its_count_at_the_end() -> None:
    log = io.StringIO()
    bar = progress_bar(desc="images", stream=log)
    for _ in range(7):
        bar.update(3)
    bar.set_postfix(loss="0.125")
    bar.close()
    bar.close()  # once
    lines = log.getvalue().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("images 21, ")
    assert lines[0].endswith(", loss 0.125")


def test_a_resumed_run_counts_from_where_it_was() -> None:
    log = io.StringIO()
    bar = progress_bar(total=10, initial=6, desc="scenes", stream=log)
    for _ in range(4):
        bar.update(1)
    bar.close()
    lines = log.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "scenes 7/10 (70 %)",
        "scenes 8/10 (80 %)",
        "scenes 9/10 (90 %)",
        "scenes 10/10 (100 %)",
    ]


def test_a_terminal_gets_the_redrawn_bar() -> None:
    tty = Terminal()
    assert list(progress_bar(range(5), desc="drops", stream=tty)) == [0, 1, 2, 3, 4]
    assert "\r" in tty.getvalue()
    assert "5/5" in tty.getvalue()


def test_a_disabled_bar_iterates_silently() -> None:
    log = io.StringIO()
    assert list(progress_bar(range(3), desc="grasps", disable=True, stream=log)) == [0, 1, 2]
    assert log.getvalue() == ""


def test_run_map_writes_plain_lines_to_a_log(capsys) -> None:
    results = list(run_map(_square, range(200), desc="episodes", unit="episode"))
    assert results == [x * x for x in range(200)]
    err = capsys.readouterr().err
    assert "\r" not in err
    assert 1 <= len(err.splitlines()) <= 11
    assert err.splitlines()[-1].startswith("episodes 200/200 (100 %)")
