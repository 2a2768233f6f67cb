"""Growable arrays for streams read one message at a time: appending is amortised O(1)
(capacity doubled when full) and the filled part is read as a view, without a copy."""
from __future__ import annotations

import numpy as np


class Column:
    """Rows of one shape (``width`` None: scalars) appended one at a time."""

    def __init__(self, width: int | None = None, dtype=float, capacity: int = 256):
        shape = (capacity,) if width is None else (capacity, width)
        self._a = np.empty(shape, dtype=dtype)
        self.n = 0

    def append(self, row) -> None:
        if self.n == len(self._a):
            grown = np.empty((2 * len(self._a), *self._a.shape[1:]), dtype=self._a.dtype)
            grown[:self.n] = self._a[:self.n]
            self._a = grown
        self._a[self.n] = row
        self.n += 1

    def view(self, n: int | None = None) -> np.ndarray:
        """The first ``n`` rows (default all), a view."""
        return self._a[:self.n if n is None else n]

    def last(self):
        return self._a[self.n - 1]

    def __len__(self) -> int:
        return self.n
