"""The learning rate of a training run: constant (``--lr``), or annealed along a half cosine (``--lr-end``).

A *phase* is one ``vlocnetpp train`` command: it starts at the step the run is at (0, or the step it
resumes from) with ``lr`` and, when ``end`` is set, reaches ``end`` at ``total`` along
``end + (lr - end) (1 + cos(pi (step - start) / (total - start))) / 2``. The phase is saved with the
training state, so an interrupted phase resumed with the same ``--lr``, ``--lr-end`` and ``--steps``
continues the same curve exactly; other values start a new phase at the resumed step (the recipe's
schedule entries: ``{steps: 6000, lr: 1e-3, lr_end: 1e-5}``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class LearningRatePhase:
    """``lr`` from step ``start`` on; annealed to ``end`` at step ``total`` when ``end`` is not None."""

    start: int
    lr: float
    end: float | None
    total: int

    def at(self, step: int) -> float:
        """The rate of the optimiser update that takes the run from ``step`` to ``step + 1``."""
        if self.end is None or self.total <= self.start:
            return self.lr
        progress = min(max((step - self.start) / (self.total - self.start), 0.0), 1.0)
        return self.end + (self.lr - self.end) * 0.5 * (1.0 + math.cos(math.pi * progress))

    def continues(self, saved: dict | None) -> LearningRatePhase:
        """This phase, or the ``saved`` one (a dict of :meth:`to_dict`) when it has the same rates and end step."""
        if saved and (saved.get("lr"), saved.get("end"), saved.get("total")) == (self.lr, self.end, self.total):
            return LearningRatePhase(int(saved["start"]), self.lr, self.end, self.total)
        return self

    def to_dict(self) -> dict:
        return asdict(self)
