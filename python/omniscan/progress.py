"""Progress objects for the stages' ``progress=`` argument.

A stage calls whichever of these methods its progress object has:
``start(label, total, unit)`` as a piece of work begins (``total`` 0: not
known), ``set(done)``, ``advance()``, ``message(text)`` (the figures so
far), ``finish()``, and ``note(line)`` (what the stage decided: reused,
resumed). Calls come from the library's worker threads, with the GIL held.
"""

from __future__ import annotations

from typing import Any, Callable, Optional


class Callback:
    """Calls ``fn(label, done, total)`` as the work advances."""

    def __init__(self, fn: Callable[[str, int, int], Any]) -> None:
        self._fn = fn
        self._label = ""
        self._total = 0
        self._done = 0

    def start(self, label: str, total: int, unit: str) -> None:
        self._label, self._total, self._done = label, total, 0
        self._fn(label, 0, total)

    def set(self, done: int) -> None:
        self._done = done
        self._fn(self._label, done, self._total)

    def advance(self) -> None:
        self.set(self._done + 1)


class Tqdm:
    """Draws each piece of work as a tqdm bar (``pip install tqdm``)."""

    def __init__(self, **tqdm_options: Any) -> None:
        from tqdm.auto import tqdm  # imported here: tqdm is optional

        self._tqdm = tqdm
        self._options = tqdm_options
        self._bar: Optional[Any] = None

    def start(self, label: str, total: int, unit: str) -> None:
        self.finish()
        self._bar = self._tqdm(total=total or None, desc=label, unit=f" {unit}", **self._options)

    def set(self, done: int) -> None:
        if self._bar is not None:
            self._bar.n = done
            self._bar.refresh()

    def advance(self) -> None:
        if self._bar is not None:
            self._bar.update(1)

    def message(self, text: str) -> None:
        if self._bar is not None:
            self._bar.set_postfix_str(text)

    def note(self, line: str) -> None:
        self._tqdm.write(line)

    def finish(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
