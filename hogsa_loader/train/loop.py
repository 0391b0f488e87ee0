"""The step loop shared by the trainers (HOGS, SRM)."""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, Optional

from torch import Tensor
from tqdm import tqdm

from hogsa_loader.io.locks import writer_lock
from hogsa_loader.train.run_folder import (
    commit_checkpoint,
    latest_checkpoint,
    read_trainer_state,
    save_trainer_state,
    start_run,
)

__all__ = ["StepLoop"]


class StepLoop(ABC):
    """Base of a trainer that trains step by step in a run folder with checkpoints.

    :meth:`run_steps` starts (or continues) the run folder, evaluates at step 0, trains up to
    ``cfg.optim.iters`` steps (evaluating every ``cfg.run.eval_every`` and checkpointing every
    ``cfg.run.ckpt_every`` steps), then evaluates and checkpoints the last step.

    :meth:`save_checkpoint` and :meth:`resume` write and read the loop's state (step,
    history, evaluations, training time) next to what the subclass keeps
    (:meth:`_save_state`, :meth:`_load_state`).

    A subclass sets ``cfg`` (a grouped config with ``RESUMABLE``, ``defaults()`` and
    ``to_json()``), ``out``, ``progress``, ``step``, ``history``, ``evals``, ``_train_time``
    and ``resumed``, and provides ``train_step()``, ``evaluate()`` and the hooks below (to
    stop early, :meth:`_out_of_time`).
    """

    #: Progress-bar label.
    desc = "train"

    @abstractmethod
    def _eval_point(self, ev: dict[str, Any]) -> dict[str, Any]:
        """What :attr:`evals` keeps of an evaluation."""
        raise NotImplementedError

    @abstractmethod
    def _postfix(self, terms: dict[str, float]) -> dict[str, str]:
        """Progress-bar figures of a step's loss terms."""
        raise NotImplementedError

    @abstractmethod
    def _eval_message(self, ev: dict[str, Any]) -> str:
        """The line written after an evaluation during training (``evals`` holds its point)."""
        raise NotImplementedError

    @abstractmethod
    def _save_state(self, folder: Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """Write the models into a checkpoint folder; the tensors (optimiser moments, RNG
        states) and JSON-able state the trainer adds to the loop's."""
        raise NotImplementedError

    @abstractmethod
    def _load_state(self, folder: Path, state: dict[str, Any], tensors: dict[str, Tensor]) -> None:
        """Restore what :meth:`_save_state` kept from a checkpoint folder and its trainer state."""
        raise NotImplementedError

    def _out_of_time(self) -> Optional[str]:
        """A message when the run must stop before its next step; None to go on."""
        return None

    def run_steps(self, overwrite: bool) -> dict[str, Any]:
        """Train to ``cfg.optim.iters`` steps (from the current step); the final evaluation.

        Args:
            overwrite: when the run was not resumed and its folder holds checkpoints, empty
                the folder and start again (otherwise :class:`RunExistsError`).
        """
        Path(self.out).mkdir(parents=True, exist_ok=True)
        with writer_lock(self.out, what="this run"):  # two --resume of one run: the second is refused
            return self._run_steps(overwrite)

    def _run_steps(self, overwrite: bool) -> dict[str, Any]:
        cfg = self.cfg
        start_run(self.out, resumed=self.resumed, overwrite=overwrite, config=cfg.to_json())
        if self.step == 0 and not self.evals:
            self.evals.append(self._eval_point(self.evaluate()))
        bar = tqdm(
            total=cfg.optim.iters, initial=self.step, disable=not self.progress, desc=self.desc, dynamic_ncols=True
        )
        while self.step < cfg.optim.iters:
            stop = self._out_of_time()
            if stop is not None:
                bar.write(stop)
                break
            self._one_step(bar)
        bar.close()
        final = self.evaluate()
        if not self.evals or self.evals[-1]["step"] != self.step:
            self.evals.append(self._eval_point(final))
        self.save_checkpoint()
        return final

    def _one_step(self, bar: tqdm) -> None:
        """A training step, timed and recorded, then the evaluation and checkpoint it is due."""
        cfg = self.cfg
        t0 = time.perf_counter()
        terms = self.train_step()
        self._train_time += time.perf_counter() - t0
        self.history.append(terms)
        bar.update(1)
        bar.set_postfix(**self._postfix(terms))
        if cfg.run.eval_every > 0 and self.step % cfg.run.eval_every == 0 and self.step < cfg.optim.iters:
            ev = self.evaluate()
            self.evals.append(self._eval_point(ev))
            bar.write(self._eval_message(ev))
        if cfg.run.ckpt_every > 0 and self.step % cfg.run.ckpt_every == 0 and self.step < cfg.optim.iters:
            self.save_checkpoint()

    def save_checkpoint(self) -> Path:
        """Write ``checkpoints/step_N/`` then point ``latest.json`` at it (atomic); older step
        folders are removed."""
        folder = self.out / "checkpoints" / f"step_{self.step:07d}"
        folder.mkdir(parents=True, exist_ok=True)
        tensors, extra = self._save_state(folder)
        state = {
            "step": self.step,
            "history": self.history,
            "evals": self.evals,
            "train_time_s": self._train_time,
            **extra,
        }
        save_trainer_state(folder, tensors, state)
        commit_checkpoint(folder, self.step)
        return folder

    def resume(self) -> bool:
        """Load the latest checkpoint of the run folder (exact continuation); False when there is none.

        Raises:
            ValueError: the run's saved settings differ (outside the config's ``RESUMABLE``).
            AssetError: a malformed, torn or corrupt checkpoint file (named), including
                optimiser or model state that does not fit the trainer's.
        """
        cls = type(self.cfg)
        folder = latest_checkpoint(self.out, self.cfg.to_json(), cls.RESUMABLE, cls.defaults())
        if folder is None:
            return False
        state, tensors = read_trainer_state(folder)
        self._load_state(folder, state, tensors)
        self.step = int(state["step"])
        self.history = state["history"]
        self.evals = state["evals"]
        self._train_time = float(state["train_time_s"])
        self.resumed = True
        return True
