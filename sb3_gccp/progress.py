"""Progress bars that also read well in a log file.

On a terminal a bar is redrawn in place as usual. When stderr is a file or a pipe (``nohup ... &``, CI),
tqdm's carriage-return redraws would pile up on one line, so the bar instead writes one plain line at
most every :data:`LOG_INTERVAL` seconds, and a last one when it closes.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any, TypeVar

from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

T = TypeVar("T")

LOG_INTERVAL = 60.0
"""Seconds between progress lines when stderr is not a terminal."""


class _LogLines:
    """A file for tqdm that turns each redraw into one line of stderr (a repeated line only once)."""

    def __init__(self) -> None:
        self._last = ""

    def write(self, text: str) -> None:
        line = text.replace("\r", "").strip()
        if line and line != self._last:
            sys.stderr.write(line + "\n")
            self._last = line

    def flush(self) -> None:
        sys.stderr.flush()


def new_bar(iterable: Iterable[T] | None = None, enabled: bool = True, **kwargs: Any) -> tqdm:
    """A tqdm bar over ``iterable`` (or updated by hand), live on a terminal, a line a minute in a log.

    :param iterable: what to iterate over, or None for a bar updated with ``update()``
    :param enabled: False gives a silent bar
    :param kwargs: tqdm's (``total``, ``desc``, ``unit``, ``initial``, ...)
    """
    if not enabled or sys.stderr.isatty():
        return tqdm(iterable, disable=not enabled, **kwargs)
    return tqdm(
        iterable, file=_LogLines(), mininterval=LOG_INTERVAL, maxinterval=LOG_INTERVAL, ascii=True, **kwargs
    )


class StepBar(BaseCallback):
    """SB3 callback: a :func:`new_bar` over the environment steps of ``model.learn``.

    SB3's own ``progress_bar=True`` draws with rich, which shows nothing in a log file until the end.

    :param total: the steps the bar counts to (``learn``'s total timesteps)
    """

    def __init__(self, total: int) -> None:
        super().__init__()
        self.total = total
        self._bar: tqdm | None = None

    def _on_training_start(self) -> None:
        self._bar = new_bar(total=self.total, initial=self.num_timesteps, unit="step")

    def _on_step(self) -> bool:
        assert self._bar is not None
        self._bar.update(self.training_env.num_envs)
        return True

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()
