"""Progress bars for the library's staged progress callbacks (``progress(description, total)``).

Bars are drawn only when stderr is a terminal (tqdm's ``disable=None``): a CI log or a redirected
run gets no bar fragments. :data:`ON_TERMINAL` is the value every ``tqdm`` of the CLI passes."""

from __future__ import annotations

from collections.abc import Callable

from tqdm import tqdm

#: tqdm's ``disable=None``: draw the bar only when the output is a terminal
ON_TERMINAL = None


class StageBars:
    """One tqdm bar per stage; starting a stage closes the previous one. Use as a context manager."""

    def __init__(self, unit: str = "item", disable: bool = False):
        self.unit, self.disable = unit, disable
        self._bar: tqdm | None = None

    def __call__(self, description: str, total: int) -> Callable[[int], None]:
        self.close()
        self._bar = tqdm(total=total, desc=description, unit=self.unit, leave=False,
                         disable=True if self.disable else ON_TERMINAL,
                         unit_scale=True)
        return self._bar.update

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> StageBars:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
