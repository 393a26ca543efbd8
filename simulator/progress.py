"""A progress bar of simulated time against real time: ``sim 3.2 s / 8.0 s, 1.4x real time``
(tqdm's own rate, ``ms/s``, read as a rate of milliseconds)."""
from __future__ import annotations

import time


class SimProgress:
    """``update(k)`` after simulated step ``k`` (of ``n_steps`` of ``dt_s``); redraws every
    ``every`` steps. A context manager; ``enabled=False`` makes it do nothing."""

    def __init__(self, name: str, n_steps: int, dt_s: float, *, enabled: bool = True, every: int = 250):
        self.n_steps, self.dt_s, self.every = n_steps, dt_s, every
        self._bar = None
        if enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=round(n_steps * dt_s, 3), desc=f"sim {name}", leave=False, mininterval=0.5,
                             bar_format="{desc}: {bar} sim {n:.1f} s / {total:.1f} s{postfix}")
        self._t0 = time.perf_counter()

    def update(self, k: int) -> None:
        bar = self._bar
        if bar is None or k % self.every:
            return
        sim_s = k * self.dt_s
        wall = time.perf_counter() - self._t0
        bar.n = round(sim_s, 3)
        bar.set_postfix_str(f"{sim_s / wall:.1f}x real time" if wall > 0 else "", refresh=False)
        bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "SimProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
