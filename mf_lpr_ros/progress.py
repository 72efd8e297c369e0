"""Progress of long offline work: a tqdm bar on a terminal, one summary line in a log.

Where stderr is not a terminal (a log file, CI, a launch file's output) a bar would write
thousands of carriage-return lines; there each loop ends with one line instead. The environment
variable MF_LPR_PROGRESS=bar or =line overrides the choice.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Iterable, Iterator

from tqdm import tqdm

PROGRESS_ENV = "MF_LPR_PROGRESS"


class SummaryLine:
    """Iterates like tqdm, silently, then writes '<desc>: N <unit> in T s' to stderr."""

    def __init__(self, iterable: Iterable, desc: str, unit: str) -> None:
        self.iterable, self.desc, self.unit = iterable, desc, unit

    def set_postfix_str(self, text: str) -> None:
        """Nothing is shown while it runs: the line comes at the end."""

    def __iter__(self) -> Iterator:
        started, count = time.monotonic(), 0
        for item in self.iterable:
            count += 1
            yield item
        print(f"{self.desc}: {count} {self.unit} in {time.monotonic() - started:.1f} s",
              file=sys.stderr, flush=True)


def progress_bar(iterable: Iterable, *, desc: str, unit: str = "it", total: int | None = None,
             enabled: bool = True):
    """iterable with a progress bar on a terminal, a summary line elsewhere, or as it is when
    not enabled (--quiet)."""
    if not enabled:
        return _Silent(iterable)
    mode = os.environ.get(PROGRESS_ENV) or ("bar" if sys.stderr.isatty() else "line")
    if mode == "bar":
        return tqdm(iterable, desc=desc, unit=unit, total=total)
    return SummaryLine(iterable, desc, unit)


class _Silent:
    """No output at all (--quiet), with the bar's interface."""

    def __init__(self, iterable: Iterable) -> None:
        self.iterable = iterable

    def set_postfix_str(self, text: str) -> None:
        """Nothing is shown."""

    def __iter__(self) -> Iterator:
        return iter(self.iterable)
