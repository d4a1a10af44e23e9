"""Progress bars on a terminal (never in logs): per item, or over a command's named stages."""

from __future__ import annotations

import sys

from tqdm import tqdm


class _Tqdm(tqdm):
    """tqdm without its monitor thread (it only tunes the refresh of bars that stall).

    A process that runs one thread may fork its background compilation
    (:func:`plenopiv.workflow.precompile.can_fork`).
    """

    monitor_interval = 0


def _progress_bar(total: int, desc: str, quiet: bool):
    # disable=None: tqdm shows the bar only when stderr is a terminal (never in logs)
    bar = _Tqdm(total=total, desc=desc, unit="", disable=True if quiet else None, leave=False,
               file=sys.stderr, dynamic_ncols=True)
    return bar, (lambda n: bar.update(n))


class _StageBar:
    """One progress bar over a command's named stages, on a terminal only.

    ``stages`` maps each stage the library reports (``progress(stage, fraction)``) to its
    expected share of the time; a reported stage counts for the longest listed name it starts
    with ("piv pass 2/3" for "piv"). The bar shows the stage and the overall percentage, and
    never goes back. A stage not listed only changes the text.
    """

    def __init__(self, desc: str, stages: dict[str, float], quiet: bool):
        self.desc = desc
        self.bar = _Tqdm(total=100, desc=desc, disable=True if quiet else None, leave=False,
                        file=sys.stderr, dynamic_ncols=True,
                        bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}")
        total = float(sum(stages.values())) or 1.0
        self.span, acc = {}, 0.0
        for name, weight in stages.items():
            self.span[name] = (acc / total, weight / total)
            acc += weight

    def __call__(self, stage: str, fraction: float = 0.0) -> None:
        self.bar.set_description_str(f"{self.desc}: {stage}", refresh=False)
        names = [k for k in self.span if stage.startswith(k)]
        if names:
            lo, width = self.span[max(names, key=len)]
            n = int(100 * (lo + width * min(max(float(fraction), 0.0), 1.0)))
            self.bar.n = max(self.bar.n, n)
        self.bar.refresh()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Remove the bar."""
        self.bar.close()
