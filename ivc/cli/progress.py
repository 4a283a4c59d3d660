"""Progress bars for the library's staged progress callbacks (``progress(description, total)``)."""

from __future__ import annotations

from collections.abc import Callable

from tqdm import tqdm


class StageBars:
    """One tqdm bar per stage; starting a stage closes the previous one. Use as a context manager."""

    def __init__(self, unit: str = "item", disable: bool = False):
        self.unit, self.disable = unit, disable
        self._bar: tqdm | None = None

    def __call__(self, description: str, total: int) -> Callable[[int], None]:
        self.close()
        self._bar = tqdm(total=total, desc=description, unit=self.unit, leave=False, disable=self.disable,
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
