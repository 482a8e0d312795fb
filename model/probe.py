"""A fit's best state (``Probe``: scored on fixed planes and seeds, kept, put back at the end)
and its first result published while it goes on (``Interim``). Both read and write the
training state of model/train.py's ``Run``.
"""

from __future__ import annotations

import json

import numpy as np
import torch

from model.device import autocast
from model.slices import lattice_partners, random_planes, render_slices


class Probe:
    """A fit keeps its best state (single mode, --probe-every), scored by its own objective
    on fixed planes and seeds, not the random ones of training, whose loss is too noisy to
    compare. A short fit at a fit's learning rate can first move away from a code that
    already matched well. Every score goes to log.jsonl as ``{"step", "probe"}``."""

    def __init__(self, run):  # noqa: ANN001 (a model.train.Run)
        cfg, self.run = run.cfg, run
        rng = np.random.default_rng(12345)
        origins, axes = random_planes(4, rng, oblique_fraction=cfg.oblique, dims=cfg.dims, extent=run.extent,
                                      grain=cfg.grain, photo_plane=bool(cfg.lattice))
        seeds = torch.arange(4, dtype=torch.int64) + 7
        self.pairs = run.objective.pairs  # as in training: two planes and their lattice partners
        if self.pairs:
            origins = torch.cat([origins[:2], lattice_partners(origins[:2], cfg.lattice, rng)])
            seeds = seeds[:2].repeat(2)
        self.origins, self.axes, self.seeds = origins.to(run.device), axes.to(run.device), seeds.to(run.device)
        saved = run.probe_best
        if saved is not None:  # a resumed pause starts from the best state before it, without a score:
            # one costs 1.2-1.6 s of the fit lane, and the state it would score was scored at the pause
            # or is a few steps from the last scored one (the next scheduled probe scores it)
            self.best_score, self.best = saved["score"], {key: saved[key] for key in ("model", "code", "step")}
        else:
            self.best_score, self.best = self.score(), self.snapshot()
            self.log(self.best_score)

    def saved_best(self) -> dict:
        """The best state and its score, for a paused fit's checkpoint."""
        return {"score": self.best_score, **self.best}

    def score(self) -> float:
        """The objective on the fixed planes, at twice the training patch size. Rendered in the
        run's precision, scored as training scores (outside autocast: the objective runs its VGG in
        that precision itself and keeps its colour moments and Gram matrices float32). Scored inside
        it, a bfloat16 colour covariance of the validation gravel's muted fit (seed 2) came out not
        positive-definite and its Cholesky failed, ending the fit; and bfloat16 Gram entries are off
        by up to 0.4%, a good fit's whole error, when the probe compares nearby states."""
        with torch.no_grad():
            with autocast(self.run.device, self.run.precision):
                patches = render_slices(self.run.model.field, self.run.codes.expand(4, -1), self.seeds, self.origins,
                                        self.axes, self.run.cfg.patch * 2).float()
            return float(self.run.objective(patches, np.zeros(4, dtype=np.int64), pairs=self.pairs))

    def snapshot(self) -> dict:
        run = self.run
        return {"model": {k: v.detach().clone() for k, v in run.model.state_dict().items()},
                "code": run.codes.detach().clone(), "step": run.step}

    def log(self, score: float) -> None:
        self.run.log.write(json.dumps({"step": self.run.step, "probe": round(score, 5)}) + "\n")

    def update(self) -> None:
        """Score the current state; keep it if it beats the best so far."""
        score = self.score()
        self.log(score)
        if score < self.best_score:
            self.best_score, self.best = score, self.snapshot()

    def restore_best(self) -> dict:
        """Put the best weights and code back; returns {'score', 'step'} for the checkpoint."""
        self._load(self.best)
        return {"score": self.best_score, "step": self.best["step"]}

    def lend_best(self, use) -> None:  # noqa: ANN001
        """``use(model, code, step)`` with the best state in the model (code: float32 [1, C], a
        copy), then the training state put back: a fit's interim exports what it would end on now."""
        current = self.snapshot()
        self._load(self.best)
        try:
            use(self.run.model, self.run.codes.detach().clone(), self.best["step"])
        finally:
            self._load(current)
            self.run.model.train()  # an export leaves its module in eval mode

    def _load(self, state: dict) -> None:
        self.run.model.load_state_dict(state["model"])  # in place: the optimiser keeps its parameters
        self.run.codes.data.copy_(state["code"])


class Interim:
    """A fit's first result, published while it goes on (``train(interim=...)``): at the first
    probe at least ``seconds`` into the run, ``publish(model, code, step)`` gets the best state
    so far, once. An upload's refinement serves it, so its tiles look like the photo seconds
    into the fit instead of at its end.

    ``start_counts``: the start (step 0) may be that state. A fit that builds structure in
    (a lattice's mean cell, a grain, a lean) starts on a sampler the upload's encoder tiles
    lack, and when no trained state beats it yet that start is the fit's best answer: the
    validation grass's 70-s and 4-min fits both kept it. Without structure the start is the
    upload's own sampler, and publishing it would call the encoder's tiles refined."""

    def __init__(self, seconds: float, publish, start_counts: bool = False):  # noqa: ANN001
        self.seconds, self.publish, self.done, self.asked = float(seconds), publish, False, False
        self.start_counts = start_counts

    def due(self, elapsed: float) -> bool:
        """True once, at the first step ``seconds`` in, published or not: a probe then, off the
        probe's schedule, if none has published yet (so the interim comes at its second and not
        up to ``--probe-every`` steps later: 25 steps are 12 s of a CPU fit), and the fit's pause
        asked then. A scheduled probe that started just before the second publishes after it;
        the step after it is still due, or that fit never paused and held the uploads behind it
        for its whole budget."""
        if self.asked or elapsed < self.seconds:
            return False
        self.asked = True
        return True

    def offer(self, probe: Probe, elapsed: float) -> None:
        """Called after each probe score, ``elapsed`` seconds into the run."""
        if self.done or elapsed < self.seconds or (probe.best["step"] == 0 and not self.start_counts):
            return
        self.done = True
        probe.lend_best(self.publish)
