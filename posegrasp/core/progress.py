"""Progress of long loops: a tqdm bar on a terminal, plain lines in a log.

A tqdm bar redraws itself with carriage returns, which a terminal overwrites in place but a log
file keeps, all on one line. `progress_bar` shows the bar only when its stream is a terminal;
else it writes one plain line each time another tenth of the work is done (or, when the total is
unknown or the steps are slow, every `PlainProgress.interval_s` seconds) and one at the end::

    episodes 12/30 (40 %), 35 s
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator, Sized
from typing import Any, Protocol, TextIO

from tqdm import tqdm

from posegrasp.core.errors import StateError

#: Seconds between two plain lines when no tenth of the work has been done in between.
PLAIN_INTERVAL_S = 60.0


class ProgressBar(Protocol):
    """What the loops use of a bar: iterate it, count, annotate, close."""

    def __iter__(self) -> Iterator[Any]: ...

    def update(self, n: int = 1) -> Any: ...

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, **kwargs: Any) -> None: ...

    def close(self) -> None: ...


class PlainProgress:
    """A progress report in whole lines, for a stream that is not a terminal.

    Args:
        iterable: what to iterate, or None to count with `update`.
        total: items in all (default: ``len(iterable)`` when it has one).
        desc: what is counted, at the start of each line.
        initial: items already done (a resumed run).
        stream: where the lines go.
        interval_s: at most this long between two lines while work goes on [s].
    """

    def __init__(
        self,
        iterable: Iterable[Any] | None = None,
        *,
        total: int | None = None,
        desc: str | None = None,
        initial: int = 0,
        stream: TextIO,
        interval_s: float = PLAIN_INTERVAL_S,
    ) -> None:
        if total is None and isinstance(iterable, Sized):
            total = len(iterable)
        self.iterable = iterable
        self.total = total
        self.desc = desc or "progress"
        self.n = initial
        self.stream = stream
        self.interval_s = interval_s
        self.postfix = ""
        self._start = self._last = time.monotonic()
        self._tenth = self._tenths(initial)
        self._closed = False

    def _tenths(self, n: int) -> int:
        return 10 * n // self.total if self.total else 0

    def _line(self) -> None:
        elapsed = time.monotonic() - self._start
        count = f"{self.n}" if self.total is None else f"{self.n}/{self.total}"
        pct = f" ({100 * self.n // self.total} %)" if self.total else ""
        tail = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc} {count}{pct}, {elapsed:.0f} s{tail}", file=self.stream, flush=True)
        self._last = time.monotonic()

    def update(self, n: int = 1) -> None:
        """Count `n` more items; write a line when another tenth is done or `interval_s` has
        passed since the last one."""
        self.n += n
        tenth = self._tenths(self.n)
        if tenth > self._tenth or time.monotonic() - self._last >= self.interval_s:
            self._tenth = tenth
            if self.total is None or self.n < self.total:  # the last line is `close`'s
                self._line()

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, **kwargs: Any) -> None:
        """Values written at the end of the next line (e.g. the running loss)."""
        values = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k} {v}" for k, v in values.items())

    def close(self) -> None:
        """Write the last line (once)."""
        if not self._closed:
            self._closed = True
            self._line()

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise StateError("this progress counts with update(); it has nothing to iterate")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Silent:
    """A disabled bar: iterates and counts, writes nothing."""

    def __init__(self, iterable: Iterable[Any] | None) -> None:
        self.iterable = iterable

    def __iter__(self) -> Iterator[Any]:
        return iter(self.iterable if self.iterable is not None else ())

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, **kwargs: Any) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    total: int | None = None,
    desc: str | None = None,
    unit: str = "it",
    initial: int = 0,
    disable: bool = False,
    leave: bool = True,
    mininterval: float = 0.1,
    stream: TextIO | None = None,
) -> ProgressBar:
    """A progress bar over `iterable` (or counted with ``update``): tqdm's on a terminal, plain
    lines (`PlainProgress`) on any other stream.

    Args:
        iterable: what to iterate, or None to count with ``update(n)``.
        total: items in all (default: ``len(iterable)`` when it has one).
        desc: what is counted.
        unit: the unit of the count.
        initial: items already done (a resumed run).
        disable: show nothing.
        leave: keep the terminal bar when done (plain lines always stay).
        mininterval: the terminal bar's least time between redraws [s].
        stream: where it shows (default: standard error).

    Returns:
        The bar: iterate it, or call ``update``, ``set_postfix`` and ``close``.
    """
    stream = sys.stderr if stream is None else stream
    if disable:
        return _Silent(iterable)
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return tqdm(
            iterable,
            total=total,
            desc=desc,
            unit=unit,
            initial=initial,
            leave=leave,
            mininterval=mininterval,
            file=stream,
            dynamic_ncols=True,
        )
    return PlainProgress(iterable, total=total, desc=desc, initial=initial, stream=stream)
