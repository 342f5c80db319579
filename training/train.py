"""Train the networks stage by stage, then export the runtime's weights file.

    python -m training.train {skr,refine,denoise,skin,smrm,all} --recipe cpu --data data
                             --out runs/cpu
                             [--resume | --overwrite] [--device cpu|cuda] [--threads N]
                             [--init WEIGHTS]
                             [--scratch STAGES] [--set KEY=VALUE ...] [--pack FILE]
                             [--online KEY=VALUE ...] [--stop-at STEP] [--stage-seconds S]

Each stage writes into --out: ``<stage>.pt`` (checkpoint, written atomically every eval),
``<stage>.csv`` (losses and validation metrics), ``<stage>.png`` (their plot). ``all`` then
exports ``weights.npz`` (minretarget's format) recording the recipe, the data and the commit.
Stages may be listed (``skr,smrm``); with ``--init WEIGHTS`` training starts from an exported
file, stages not listed keep its networks, and the export happens after any stages;
``--scratch smrm`` retrains a stage from random initialisation while the others come from
--init. ``--set smrm.clip_frames=10`` overrides one recipe value (ablations); the run's
recipe.json and the weights' metadata record the recipe as run.
A folder that holds an earlier run is refused unless ``--resume`` continues it (each
unfinished stage from its checkpoint; finished stages are skipped; the recipe and --init
must be the ones it started with, except that stages may be given more steps, and a stage
whose files were deleted is trained afresh with this recipe; a stage given more steps is
refused while one that learned its output has a checkpoint) or ``--overwrite`` deletes it
first. ``--stop-at STEP`` stops each stage there, to resume
later, and the stages after the first that stops wait for it (refine and denoise learn
SKR's errors); ``--stage-seconds S`` fits each stage's schedule to S seconds of wall clock
instead (a lent GPU's few minutes). Ctrl-C stops a stage after the step in progress and
checkpoints it; a loss or validation metric that is not finite stops it with its last
good checkpoint kept (delete the stage's files and --resume with another recipe value).
From the command line bad input is one line naming it (exit status 1), not a traceback.
``--pack FILE`` (a data pack, ``training.data.pack``): SKR poses fresh frames for every batch
on the training device (``training.data.online``) instead of reading ``skr_train.npz`` (for a
long run on a GPU, which would otherwise see a build's frames over and over), drawn as a
default build draws them or with ``--online crossed_fraction=0.15`` and the like; the other
stages read --data as ever.
Validation uses the held-out training subjects and bodies (``*_val.npz``), never the test split.
"""
import argparse
import csv
import dataclasses
import io
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np
import torch
from tqdm import tqdm

from minretarget.atomic import atomic_write
from minretarget.cli import int_at_least, positive_float, stop_between_steps
from minretarget.formats.npz import load_npz
from minretarget.conventions import NUM_JOINTS
from minretarget.metrics import ACCELERATION_FRAMES
from minretarget.refine import refine_joints
from minretarget.skr import regress_joints
from minretarget.smoothing import Smoothing, smooth_joints
from minretarget.weights import file_sha256, load_weights
from training.data.datasets import BuildConfig
from training.data.online import OnlineFrames
from training.data.pack import load_pack, without_broken_ankles
from training.export import (export_weights, import_weights, refine_runtime_weights,
                             skr_runtime_weights)
from training.kinematics import forward_kinematics
from training.losses import (denoise_losses, discriminator_loss, foot_velocity_error,
                             skin_loss, skr_loss, smrm_losses)
from training.models import (JointRefiner, MotionDiscriminator, MotionRetargeter,
                             SkeletonDenoiser, SkeletonRegressor, SkinningField)
from training.models.denoise import mirror_image
from training.recipe import load_recipe

# refine and denoise only where the config has a refiner and a denoiser
STAGES = ("skr", "refine", "denoise", "skin", "smrm")
VALIDATION_LIMIT = 2048   # validation samples per evaluation, to bound its time
PLAN_AFTER_STEPS = 16     # steps timed before a time budget first sizes a stage's schedule


class Split(dict):
    """A built dataset's arrays; one it lacks is an error naming the file."""

    def __init__(self, path, arrays):
        super().__init__(arrays)
        self.path = path

    def __missing__(self, key):
        raise ValueError(f"{self.path}: has no array {key!r} (it holds {', '.join(self)}): "
                         "rebuild the data (python -m training.data build)")


def load_split(data_dir, name, device):
    """``DIR/name.npz`` -> {key: tensor on device} (no pickle); ValueError naming the file if
    it is missing or damaged."""
    path = Path(data_dir) / f"{name}.npz"
    if not path.is_file():
        raise ValueError(f"{path} is missing: build the data first "
                         "(python -m training.data build --out DIR)")
    return Split(path, {key: torch.from_numpy(np.asarray(array, dtype=np.float32)
                                              if array.dtype.kind == "f" else array).to(device)
                        for key, array in load_npz(path).items()})


def learning_rate(step, steps, base):
    """Linear warm-up over the first 2% of steps, then cosine decay to 10% of ``base``."""
    warmup = max(1, steps // 50)
    if step < warmup:
        return base * (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return base * (0.1 + 0.45 * (1 + math.cos(math.pi * progress)))


class Limit(NamedTuple):
    """Where a stage stops short of its recipe: at a step (checkpointed, to resume), and/or
    within seconds of wall clock (its schedule cut to fit; ``Stage.run``)."""
    step: Optional[int] = None
    seconds: Optional[float] = None


def fit_steps(step, seconds_per_step, seconds_left, cap):
    """The step count a stage can reach from ``step`` with ``seconds_left`` of wall clock at
    ``seconds_per_step`` (its evaluations' share included): at most ``cap`` in all, and at
    least one more step (the last, which evaluates)."""
    more = int(seconds_left / seconds_per_step) if seconds_left > 0 else 0
    return max(step + 1, min(cap, step + more))


@dataclasses.dataclass
class StageClock:
    """A run's wall clock (``Stage.run``): when it started, at which step, and the seconds
    its evaluations took, in all and the last one."""
    started: float
    first: int
    evaluating: float = 0.0
    last_evaluation: float = 0.0


class ResumeMismatch(ValueError):
    """A checkpoint made on other training data than the resuming run's."""


def read_checkpoint(path):
    """A stage's checkpoint (``Stage.save``), without pickle; ValueError naming it if it is
    not one."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001  (pickle, zip and torch errors alike)
        raise ValueError(f"{path}: not a readable checkpoint ({type(error).__name__}); delete "
                         "it (and the stage's .csv and .png) to train the stage again") from None


class Stage:
    """The loop every stage shares: batches, schedule, logging, evaluation, checkpoints.
    ``source`` names the training data where a stage can draw from more than one (SKR: built
    frames or a pack); the checkpoint keeps it, so that a resume on other data is refused."""

    def __init__(self, name, run_dir, modules, optimizers, steps, eval_every, seed, source=None):
        self.name, self.run_dir, self.source = name, Path(run_dir), source
        self.modules, self.optimizers = modules, optimizers
        self.steps, self.eval_every = steps, eval_every
        self.recipe_steps = steps   # self.steps may be cut to fit a time budget (run)
        self.base_rates = {k: o.param_groups[0]["lr"] for k, o in optimizers.items()}
        self.generator = torch.Generator().manual_seed(seed)
        self.step = 0
        self.rows = []
        self.running = {}   # loss sums since the last evaluation
        self.running_steps = 0      # the steps summed there
        self.seconds_before = 0.0   # of the log's clock, at a resumed run's start

    @property
    def planned(self):
        """Whether a time budget cut the schedule short of the recipe's steps."""
        return self.steps < self.recipe_steps

    @property
    def checkpoint_path(self):
        return self.run_dir / f"{self.name}.pt"

    def elapsed(self, clock):
        """Seconds of the log's clock: this run's and those of the runs it resumed."""
        return self.seconds_before + time.perf_counter() - clock.started

    def save(self, clock):
        state = {"step": self.step, "rows": self.rows, "running": self.running,
                 "running_steps": self.running_steps, "seconds": self.elapsed(clock),
                 "modules": {k: m.state_dict() for k, m in self.modules.items()},
                 "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                 "generator": self.generator.get_state(), "torch_rng": torch.get_rng_state(),
                 "source": self.source, "steps": self.steps, "planned": self.planned}
        buffer = io.BytesIO()
        torch.save(state, buffer)
        with atomic_write(self.checkpoint_path) as file:
            file.write(buffer.getvalue())

    def load(self):
        state = read_checkpoint(self.checkpoint_path)
        if state["step"] > (state["steps"] if state.get("planned") else self.steps):
            raise ResumeMismatch(f"{self.checkpoint_path} is at step {state['step']}, past "
                                 f"this recipe's {self.steps}: resume with "
                                 f"{self.name}.steps of at least {state['step']}")
        if "source" in state and state["source"] != self.source:  # older checkpoints lack it
            raise ResumeMismatch(f"{self.checkpoint_path} trained on {state['source']}, this "
                                 f"run on {self.source}: resume with the same data")
        for key, module in self.modules.items():
            module.load_state_dict(state["modules"][key])
        for key, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state["optimizers"][key])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        self.step, self.rows, self.running = state["step"], state["rows"], state["running"]
        self.running_steps = state.get("running_steps", (self.step - 1) % self.eval_every + 1
                                       if self.running else 0)
        self.seconds_before = state.get("seconds", self.rows[-1]["seconds"] if self.rows
                                        else 0.0)
        if state.get("planned"):   # a schedule cut to a time budget goes on as cut
            self.steps = state["steps"]

    def batch(self, count, size):
        return torch.randint(count, (size,), generator=self.generator)

    def run(self, train_step, evaluate, resume, limit=None):
        """Call ``train_step(stage) -> {loss: float}`` until ``steps`` (or ``limit.step``, with
        a checkpoint to resume from); evaluate with ``evaluate() -> {metric: float}`` every
        ``eval_every`` steps and at the end. With ``limit.seconds``, it evaluates first too
        (the weights it starts from, and how long an evaluation takes), and the step count is
        cut to what fits that wall clock (``fit_steps``: sized after PLAN_AFTER_STEPS steps,
        twice as many, four times, ..., and at each evaluation, the final evaluation's time
        kept free), so that the learning-rate schedule still runs its course; past the
        deadline the next step is the last. Returns whether the stage is finished."""
        stop_at, seconds = limit or Limit()
        if resume and self.checkpoint_path.exists():
            self.load()
            print(f"{self.name}: resumed at step {self.step}/{self.steps}")
        elif resume:
            print(f"{self.name}: no checkpoint in {self.run_dir}: starting it")
        progress = tqdm(total=self.steps, initial=self.step, desc=self.name, unit="step")
        clock = StageClock(time.perf_counter(), self.step)
        if seconds is not None and self.step < self.steps:
            self.evaluate(evaluate, clock, progress)
        with stop_between_steps() as stop_asked:
            self._steps(train_step, evaluate, stop_at, seconds, clock, progress, stop_asked)
        if self.step < self.steps:
            self.save(clock)
        if stop_asked:          # asked during the last step: the stage is saved, stop here
            raise KeyboardInterrupt
        progress.close()
        if self.planned:
            print(f"{self.name}: {self.steps:,} of the recipe's {self.recipe_steps:,} steps, "
                  "to fit the time budget")
        for module in self.modules.values():
            module.eval()
        return self.step == self.steps

    def _steps(self, train_step, evaluate, stop_at, seconds, clock, progress, stop_asked):
        while self.step < (self.steps if stop_at is None else min(self.steps, stop_at)):
            if stop_asked:
                self.save(clock)
                raise KeyboardInterrupt
            done = self.step - clock.first
            if seconds is not None and done > 0 and (
                    (done >= PLAN_AFTER_STEPS and done & (done - 1) == 0)   # 16, 32, 64, ...
                    or time.perf_counter() - clock.started > seconds - clock.last_evaluation):
                self.plan(clock, seconds, progress)
            for key, optimizer in self.optimizers.items():
                for group in optimizer.param_groups:
                    group["lr"] = learning_rate(self.step, self.steps, self.base_rates[key])
            for module in self.modules.values():
                module.train()
            losses = train_step(self)
            bad = {k: v for k, v in losses.items() if not math.isfinite(v)}
            if bad:     # the last checkpoint, before it, is kept
                raise ValueError(f"{self.name}: loss {bad} at step {self.step + 1} (too high "
                                 f"a learning rate?); {self.checkpoint_path} keeps the last "
                                 "evaluated step")
            for key, value in losses.items():
                self.running[key] = self.running.get(key, 0.0) + value
            self.running_steps += 1
            self.step += 1
            progress.update(1)
            if self.step % self.eval_every == 0 or self.step == self.steps:
                self.evaluate(evaluate, clock, progress)
                if (seconds is not None and self.step - clock.first >= PLAN_AFTER_STEPS
                        and self.step < self.steps):
                    self.plan(clock, seconds, progress)
                self.save(clock)
                self.write_log()

    def evaluate(self, evaluate, clock, progress):
        """One row of the log: the mean losses since the last one and the metrics now."""
        for module in self.modules.values():
            module.eval()
        began = time.perf_counter()
        with torch.no_grad():
            metrics = evaluate()
        clock.last_evaluation = time.perf_counter() - began
        clock.evaluating += clock.last_evaluation
        bad = {k: v for k, v in metrics.items() if not math.isfinite(v)}
        if bad:     # not saved: the last checkpoint, before it, is kept
            raise ValueError(f"{self.name}: validation {bad} at step {self.step} (too high a "
                             f"learning rate?); {self.checkpoint_path} keeps the last good "
                             "step")
        row = {"step": self.step, "seconds": round(self.elapsed(clock), 1),
               **{k: v / max(1, self.running_steps) for k, v in self.running.items()},
               **metrics}
        self.rows.append(row)
        self.running, self.running_steps = {}, 0
        progress.set_postfix({k: f"{v:.4g}" for k, v in metrics.items()})

    def plan(self, clock, seconds, progress):
        """Cut ``steps`` to what fits ``seconds`` at this run's pace so far."""
        elapsed = time.perf_counter() - clock.started
        per_step = ((elapsed - clock.evaluating) / (self.step - clock.first)
                    + clock.last_evaluation / self.eval_every)
        steps = fit_steps(self.step, per_step, seconds - elapsed - clock.last_evaluation,
                          self.recipe_steps)
        if steps != self.steps:
            self.steps = steps
            progress.total = steps
            progress.refresh()

    def write_log(self):
        """The CSV of every evaluation row so far, and its plot."""
        keys = list(dict.fromkeys(k for row in self.rows for k in row))
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=keys)
        writer.writeheader()
        writer.writerows(self.rows)
        with atomic_write(self.run_dir / f"{self.name}.csv") as file:
            file.write(text.getvalue().encode())
        plot_log(self.rows, self.run_dir / f"{self.name}.png", self.name)


def plot_log(rows, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = [k for k in dict.fromkeys(k for row in rows for k in row)
            if k not in ("step", "seconds")]
    steps = [row["step"] for row in rows]
    columns = min(4, len(keys))
    rows_of_plots = -(-len(keys) // columns)
    figure, axes = plt.subplots(rows_of_plots, columns, figsize=(3.2 * columns,
                                                                 2.8 * rows_of_plots),
                                squeeze=False)
    for axis in axes.flat[len(keys):]:
        axis.set_visible(False)
    for axis, key in zip(axes.flat, keys):
        axis.plot(steps, [row.get(key, np.nan) for row in rows], marker=".")
        axis.set_title(key, fontsize=9)
        axis.set_xlabel("step")
        axis.set_yscale("log" if all(row.get(key, 1) > 0 for row in rows) else "linear")
    figure.suptitle(title)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=80)
    plt.close(figure)
    with atomic_write(path) as file:
        file.write(buffer.getvalue())


def subsample_points(points, count, generator):
    """(B, P, 3) -> (B, count, 3): a random subset of each cloud (a fresh one every batch)."""
    if count >= points.shape[1]:
        return points
    keys = torch.rand(points.shape[:2], generator=generator).to(points.device)
    return torch.gather(points, 1, keys.argsort(dim=1)[:, :count, None].expand(-1, -1, 3))


def mean_over_batches(count, size, function):
    """Average ``function(index tensor) -> {name: float}`` over the first ``count`` samples."""
    totals, seen = {}, 0
    for start in range(0, count, size):
        index = torch.arange(start, min(start + size, count))
        for key, value in function(index).items():
            totals[key] = totals.get(key, 0.0) + value * len(index)
        seen += len(index)
    return {k: v / seen for k, v in totals.items()}


# ----------------------------------------------------------------------------- stages

def posed_and_tpose_batch(stage, posed, tpose, size, tpose_count, keys):
    """One batch of SKR-dataset samples: ``size - tpose_count`` drawn from ``posed`` and
    ``tpose_count`` from ``tpose`` (the T-pose files), ``keys`` concatenated in that order."""
    moving = stage.batch(len(posed["points"]), size - tpose_count)
    still = stage.batch(len(tpose["points"]), tpose_count)
    return {key: torch.cat([posed[key][moving], tpose[key][still]]) for key in keys}


def joint_errors(data, name, predict):
    """{name: mean joint error (metres)} of ``predict(data, index) -> (B, J, 3)`` against
    ``data["joints"]``, over at most VALIDATION_LIMIT samples."""
    def error(index):
        return {name: float((predict(data, index) - data["joints"][index]).norm(dim=-1).mean())}
    return mean_over_batches(min(VALIDATION_LIMIT, len(data["points"])), 64, error)


def initial_models(recipe, init=None, scratch=()):
    """The networks, freshly initialised or, with ``init`` (runtime Weights), loaded from an
    exported file (its batch norms folded, see ``export.import_weights``) except the stages
    named in ``scratch`` and a refiner or denoiser ``init`` does not have, which stay fresh."""
    def fresh():
        models = {"skr": SkeletonRegressor(recipe.model), "smrm": MotionRetargeter(recipe.model),
                  "skin": SkinningField(recipe.model)}
        if recipe.model.refines:
            with torch.random.fork_rng(devices=[]):   # the other networks' draws stay as before
                torch.manual_seed(recipe.seed + 3)
                models["refine"] = JointRefiner(recipe.model)
        if recipe.model.denoises:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(recipe.seed + 4)
                models["denoise"] = SkeletonDenoiser(recipe.model)
        return models
    models = fresh()
    if init is not None:
        with torch.random.fork_rng(devices=[]):     # leave later draws (the discriminator) alone
            loaded = fresh()
        for name in ("refine", "denoise"):          # what init lacks starts fresh
            if getattr(init, name) is None:
                loaded.pop(name, None)
        import_weights(init, loaded["skr"], loaded["smrm"], loaded["skin"], loaded.get("refine"),
                       loaded.get("denoise"))
        if recipe.model.smrm_analytic_prior and not init.config.smrm_analytic_prior:
            loaded["smrm"].reset_rotation_head()   # its rotations become corrections: start at 0
        if (init.config.smrm_analytic_prior and not recipe.model.smrm_analytic_prior
                and "smrm" not in scratch):
            raise ValueError("the --init weights' SMRM predicts corrections to the analytic "
                             "rotations (smrm_analytic_prior); a recipe without the prior would "
                             "read them as whole rotations: set model.smrm_analytic_prior")
        models.update({name: loaded[name] for name in loaded if name not in scratch})
        if init.rest_pose is not None:     # fitted, not trained: a fresh SMRM gets it too
            with torch.no_grad():
                models["smrm"].rest_directions.copy_(torch.from_numpy(init.rest_pose.directions))
    return models


# What SKR's online frames are drawn as: a default build's (category power 1, no seated or
# crossed legs, 2,048-point validation clouds); validation is drawn with its seed whatever the
# recipe's, so that every run scores the same frames. ``--online KEY=VALUE`` changes the
# training draws' ONLINE_FIELDS (crossed legs, say), never validation's.
ONLINE_FRAMES = BuildConfig()
ONLINE_FIELDS = ("max_shift", "category_power", "seated_fraction", "crossed_fraction")


def online_config(assignments):
    """["crossed_fraction=0.15", ...] -> ONLINE_FRAMES with those ONLINE_FIELDS replaced;
    ValueError naming a field that is not one, or a value that is not a number or is out of
    its range."""
    changes = {}
    for assignment in assignments:
        key, equals, value = assignment.partition("=")
        if not equals or key not in ONLINE_FIELDS:
            raise ValueError(f"{assignment!r}: expected KEY=VALUE with KEY one of "
                             f"{', '.join(ONLINE_FIELDS)}")
        try:
            changes[key] = float(value)
        except ValueError:
            raise ValueError(f"{assignment!r}: {value!r} is not a number") from None
    return dataclasses.replace(ONLINE_FRAMES, **changes)


def online_changes(config):
    """How ``config``'s draws differ from ONLINE_FRAMES': "" or " with crossed_fraction=0.15"."""
    changed = [f"{k}={getattr(config, k):g}" for k in ONLINE_FIELDS
               if getattr(config, k) != getattr(ONLINE_FRAMES, k)]
    return f" with {', '.join(changed)}" if changed else ""


def online_skr_data(pack, device, config=ONLINE_FRAMES):
    """SKR's training frames drawn afresh from a data pack (``training.data.online``) as
    ``config`` says, and VALIDATION_LIMIT validation frames drawn once from its validation
    split as ONLINE_FRAMES says."""
    def frames(split, config):
        return OnlineFrames(pack.motions[split], pack.bodies[split], pack.actor_hip_height,
                            config, device)
    source = frames("val", ONLINE_FRAMES)
    poses = source.poses(VALIDATION_LIMIT, np.random.default_rng([ONLINE_FRAMES.seed, 0]))
    generator = torch.Generator(device).manual_seed(ONLINE_FRAMES.seed)
    return frames("train", config), source.clouds(*poses, ONLINE_FRAMES.points, generator)


def train_skr(recipe, data_dir, run_dir, device, resume, limit=None, model=None, pack=None,
              online=ONLINE_FRAMES):
    """SKR on the built frames (``skr_*.npz``), or with a data pack (``pack.load_pack``) on
    frames drawn afresh every batch as ``online`` (a ``BuildConfig``) says; the T-pose
    frames always come from ``skr_tpose_*.npz``."""
    stage_recipe = recipe.skr
    if pack is None:
        train, val = (load_split(data_dir, f"skr_{s}", device) for s in ("train", "val"))
    else:
        train, val = online_skr_data(pack, device, online)
    tpose_train, tpose_val = (load_split(data_dir, f"skr_tpose_{s}", device)
                              for s in ("train", "val"))
    model = (model or SkeletonRegressor(recipe.model)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=stage_recipe.learning_rate)
    source = ("built frames" if pack is None else f"frames drawn from pack {pack.sha256}"
              + online_changes(online))
    stage = Stage("skr", run_dir, {"skr": model}, {"skr": optimizer}, stage_recipe.steps,
                  stage_recipe.eval_every, recipe.seed, source)
    tpose_count = round(stage_recipe.tpose_fraction * stage_recipe.batch_size)

    def online_batch(stage):
        """Fresh frames, as many points as the T-pose clouds (a subset is taken below); the
        draws are seeded by the step, so a resumed stage draws what it would have."""
        draws = np.random.default_rng([recipe.seed, 1, stage.step])
        generator = torch.Generator(device).manual_seed(int(draws.integers(2 ** 62)))
        moving = train.batch(stage_recipe.batch_size - tpose_count,
                             tpose_train["points"].shape[1], draws, generator)
        still = stage.batch(len(tpose_train["points"]), tpose_count)
        return {key: torch.cat([moving[key], tpose_train[key][still]]) for key in moving}

    def train_step(stage):
        batch = (posed_and_tpose_batch(stage, train, tpose_train, stage_recipe.batch_size,
                                       tpose_count, ("points", "joints"))
                 if pack is None else online_batch(stage))
        points = subsample_points(batch["points"], stage_recipe.points, stage.generator)
        loss = skr_loss(model(points), batch["joints"])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss": loss.item()}

    def evaluate():
        def predict(data, index):
            return model(data["points"][index])
        return {**joint_errors(val, "val_mpjpe", predict),
                **joint_errors(tpose_val, "val_tpose_mpjpe", predict)}

    return model, stage.run(train_step, evaluate, resume, limit)


def skr_predictions(skr_weights, points):
    """SKR's joints (N, J, 3) of clouds (N, P, 3), on ``points``' device, computed by the
    runtime (minretarget.skr) on the exported SKR (``export.skr_runtime_weights``): the same
    joints as torch's eval mode to about 1e-5 m, and on this 2-core CPU about 4.5 times
    faster than torch eager (14 s for the 2,000 validation clouds; torch took about 12
    minutes for all 22,000 clouds of the SKR datasets)."""
    joints = regress_joints(points.cpu().numpy(), skr_weights)  # one worker: BLAS has the cores
    return torch.from_numpy(joints).to(points.device)


def train_refine(recipe, data_dir, run_dir, device, resume, limit=None, model=None,
                 skr=None):
    """The joint refiner on the trained SKR's joints (computed once, on whole clouds, as the
    runtime sees them) of the SKR datasets: MSE to the true joints."""
    stage_recipe = recipe.refine
    skr_weights = skr_runtime_weights(skr.cpu().eval())             # exported once
    splits = {}
    for name in ("skr_train", "skr_val", "skr_tpose_train", "skr_tpose_val"):
        splits[name] = load_split(data_dir, name, device)
        splits[name]["skr"] = skr_predictions(skr_weights, splits[name]["points"])
    train, val = splits["skr_train"], splits["skr_val"]
    tpose_train, tpose_val = splits["skr_tpose_train"], splits["skr_tpose_val"]
    model = (model or JointRefiner(recipe.model)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=stage_recipe.learning_rate)
    stage = Stage("refine", run_dir, {"refine": model}, {"refine": optimizer},
                  stage_recipe.steps, stage_recipe.eval_every, recipe.seed + 3)
    tpose_count = round(stage_recipe.tpose_fraction * stage_recipe.batch_size)

    def train_step(stage):
        batch = posed_and_tpose_batch(stage, train, tpose_train, stage_recipe.batch_size,
                                      tpose_count, ("points", "joints", "skr"))
        # Clouds of every density the refiner should serve, from min_points to all.
        count = int(torch.randint(stage_recipe.min_points, batch["points"].shape[1] + 1, (1,),
                                  generator=stage.generator))
        points = subsample_points(batch["points"], count, stage.generator)
        loss = skr_loss(model(points, batch["skr"]), batch["joints"])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss": loss.item()}

    def evaluate():
        def refined(data, index):
            return model(data["points"][index], data["skr"][index])

        def skr_alone(data, index):
            return data["skr"][index]
        return {**joint_errors(val, "val_mpjpe", refined),
                **joint_errors(val, "val_mpjpe_skr", skr_alone),
                **joint_errors(tpose_val, "val_tpose_mpjpe", refined),
                **joint_errors(tpose_val, "val_tpose_mpjpe_skr", skr_alone)}

    return model, stage.run(train_step, evaluate, resume, limit)


def smoothed_skeletons(skr_weights, refine_weights, neighbours, points, starts):
    """The source skeletons SMRM's smoothing hands the denoiser at run time: the runtime's SKR
    (then the refiner, if any) on each cloud (N, P, 3), then each trial (frames
    starts[s]:starts[s+1]) through ``smoothing.Smoothing()`` from its first frame. (N, J, 3)."""
    clouds = points.cpu().numpy()
    joints = np.empty((len(clouds), NUM_JOINTS, 3), np.float32)
    for start in range(0, len(clouds), 1024):
        chunk = clouds[start:start + 1024]
        skeleton = regress_joints(chunk, skr_weights)
        if refine_weights is not None:
            skeleton = refine_joints(chunk, skeleton, refine_weights, neighbours)
        joints[start:start + len(chunk)] = skeleton
    starts = starts.cpu().numpy()
    for a, b in zip(starts[:-1], starts[1:]):
        previous, velocity = joints[a], np.zeros_like(joints[a])
        for t in range(a, b):
            previous, velocity = smooth_joints(joints[t], previous, velocity, Smoothing())
            joints[t] = previous
    return torch.from_numpy(joints).to(points.device)


def train_denoise(recipe, data_dir, run_dir, device, resume, limit=None, model=None,
                  skr=None, refine=None):
    """The skeleton denoiser on the smoothed skeletons of the trained SKR (and refiner) of
    whole trials (``sequences_*.npz``, computed once, as the runtime sees them): the mean
    joint error plus ``acceleration`` times the mean acceleration error plus
    ``foot_velocity`` times the feet's velocity error on the true ground contacts, against the
    true joints, on random windows; half of them mirrored (left and right swapped).
    Validation scores it as the runtime runs it, mirror-averaged."""
    stage_recipe = recipe.denoise
    skr_weights = skr_runtime_weights(skr.cpu().eval())
    refine_weights = None if refine is None else refine_runtime_weights(refine.cpu().eval())
    splits = {}
    for split in ("train", "val"):
        data = load_split(data_dir, f"sequences_{split}", device)
        data["skeleton"] = smoothed_skeletons(skr_weights, refine_weights,
                                              recipe.model.refine_neighbours, data.pop("points"),
                                              data["starts"])
        splits[split] = data
    train, val = splits["train"], splits["val"]
    starts = train["starts"].cpu()
    lengths = starts[1:] - starts[:-1]
    usable = torch.nonzero(lengths >= stage_recipe.window)[:, 0]
    if stage_recipe.window < ACCELERATION_FRAMES or not len(usable):
        raise ValueError(f"denoise.window {stage_recipe.window}: must be at least "
                         f"{ACCELERATION_FRAMES} frames (acceleration) and no longer than some "
                         "training trial")
    model = (model or SkeletonDenoiser(recipe.model)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=stage_recipe.learning_rate)
    stage = Stage("denoise", run_dir, {"denoise": model}, {"denoise": optimizer},
                  stage_recipe.steps, stage_recipe.eval_every, recipe.seed + 4)
    def train_step(stage):
        trial = usable[stage.batch(len(usable), stage_recipe.batch_size)]
        offset = (torch.rand(len(trial), generator=stage.generator)
                  * (lengths[trial] - stage_recipe.window + 1)).long()
        frames = (starts[trial] + offset)[:, None] + torch.arange(stage_recipe.window)
        skeleton, joints = train["skeleton"][frames], train["joints"][frames]
        mirrored = (torch.rand(len(trial), generator=stage.generator) < 0.5).to(device)
        skeleton = torch.where(mirrored[:, None, None, None], mirror_image(skeleton), skeleton)
        joints = torch.where(mirrored[:, None, None, None], mirror_image(joints), joints)
        denoised = model(skeleton)[0]
        position, acceleration = denoise_losses(denoised, joints)
        feet = foot_velocity_error(denoised, joints)
        loss = (position + stage_recipe.acceleration * acceleration
                + stage_recipe.foot_velocity * feet)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss": loss.item(), "position": position.item(),
                "acceleration": acceleration.item(), "foot_velocity": feet.item()}

    def evaluate():
        """Each validation trial whole, from a stream's start, as the runtime plays it."""
        def scores(x, joints):
            return [*map(float, denoise_losses(x, joints)), float(foot_velocity_error(x, joints))]
        totals, frames = torch.zeros(6), 0
        bounds = val["starts"].cpu().tolist()
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < ACCELERATION_FRAMES:
                continue
            skeleton, joints = val["skeleton"][a:b][None], val["joints"][a:b][None]
            denoised = model.mirror_averaged(skeleton)[0]      # as the runtime runs it
            totals += (b - a) * torch.tensor(scores(denoised, joints) + scores(skeleton, joints))
            frames += b - a
        totals /= max(frames, 1)
        return dict(zip(("val_mpjpe", "val_acc", "val_foot_velocity", "val_mpjpe_smoothed",
                         "val_acc_smoothed", "val_foot_velocity_smoothed"), totals.tolist()))

    return model, stage.run(train_step, evaluate, resume, limit)


def train_skin(recipe, data_dir, run_dir, device, resume, limit=None, model=None):
    stage_recipe = recipe.skin
    train, val = (load_split(data_dir, f"skin_{s}", device) for s in ("train", "val"))
    model = (model or SkinningField(recipe.model)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=stage_recipe.learning_rate)
    stage = Stage("skin", run_dir, {"skin": model}, {"skin": optimizer}, stage_recipe.steps,
                  stage_recipe.eval_every, recipe.seed + 1)

    def loss_of(data, index, joint_noise, generator=None):
        tpose_joints = data["tpose_joints"][index]
        noise = torch.randn(tpose_joints.shape, generator=generator).to(device)
        tpose_joints = tpose_joints + joint_noise * noise
        points = data["tpose_points"][index]
        weights = model(points, tpose_joints)
        return skin_loss(weights, points, data["posed_points"][index], data["rotations"][index],
                         data["root"][index], tpose_joints)

    def train_step(stage):
        index = stage.batch(len(train["tpose_points"]), stage_recipe.batch_size)
        loss = loss_of(train, index, stage_recipe.joint_noise, stage.generator)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return {"loss": loss.item()}

    def evaluate():
        generator = torch.Generator().manual_seed(0)   # the same jitter at every evaluation
        return mean_over_batches(
            min(VALIDATION_LIMIT, len(val["tpose_points"])), 32,
            lambda index: {"val_vertex_error": float(loss_of(val, index, 0.0)),
                           "val_vertex_error_jittered": float(loss_of(
                               val, index, stage_recipe.joint_noise, generator))})

    return model, stage.run(train_step, evaluate, resume, limit)


def source_noise(shape, stage_recipe, generator):
    """Noise for (B, T, J, 3) source clips, as SKR's error (see SMRMStage.input_noise_*):
    white with std ``input_noise``, or per joint a clip-constant part plus a stationary
    AR(1) part with the recipe's stds and autocorrelation."""
    white = torch.randn(shape, generator=generator)
    if not stage_recipe.input_noise_bias:
        return stage_recipe.input_noise * white
    rho = stage_recipe.input_noise_autocorrelation
    frame = [white[:, 0]]
    for t in range(1, shape[1]):
        frame.append(rho * frame[-1] + math.sqrt(1 - rho ** 2) * white[:, t])
    bias_std = torch.tensor(stage_recipe.input_noise_bias)[:, None]             # (J, 1)
    frame_std = torch.tensor(stage_recipe.input_noise_frame)[:, None]
    bias = torch.randn((shape[0], 1) + tuple(shape[2:]), generator=generator)
    return bias * bias_std + torch.stack(frame, dim=1) * frame_std


def retarget_ground_truth(rotations, root, source_tpose, target_tpose):
    """Mixamo-style ground truth: A's local rotations on B, root scaled by the hip heights.

    rotations (B, T, J, 4), root (B, T, 3), tpose (B, J, 3) with feet at y = 0 -> (B, T, J, 3).
    """
    ratio = target_tpose[:, 0, 1] / source_tpose[:, 0, 1]
    joints, _ = forward_kinematics(rotations, root * ratio[:, None, None], target_tpose[:, None])
    return joints


def train_smrm(recipe, data_dir, run_dir, device, resume, limit=None, model=None):
    stage_recipe = recipe.smrm
    train, val = (load_split(data_dir, f"smrm_{s}", device) for s in ("train", "val"))
    model = (model or MotionRetargeter(recipe.model)).to(device)
    with torch.random.fork_rng(devices=[]):     # the same critic whichever stages ran before
        torch.manual_seed(recipe.seed + 2)
        discriminator = MotionDiscriminator(recipe.model,
                                            stage_recipe.discriminator_width).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=stage_recipe.learning_rate)
    optimizer_d = torch.optim.Adam(discriminator.parameters(),
                                   lr=stage_recipe.discriminator_learning_rate)
    stage = Stage("smrm", run_dir, {"smrm": model, "discriminator": discriminator},
                  {"smrm": optimizer, "discriminator": optimizer_d}, stage_recipe.steps,
                  stage_recipe.eval_every, recipe.seed + 2)
    bodies = train["bodies_tpose_joints"]

    stored_frames = train["joints"].shape[1]
    if not 3 <= stage_recipe.clip_frames <= stored_frames:
        raise ValueError(f"smrm.clip_frames {stage_recipe.clip_frames}: must be at least 3 "
                         f"(acceleration) and at most the data's {stored_frames}-frame clips "
                         "(python -m training.data build --only smrm --clip-frames N)")

    def clips(index, generator):
        """(B, clip_frames, J, 3): a random window of each indexed clip."""
        if stage_recipe.clip_frames == stored_frames:        # whole clips: no draw
            return train["joints"][index]
        start = torch.randint(stored_frames - stage_recipe.clip_frames + 1, (len(index),),
                              generator=generator)
        frames = start[:, None] + torch.arange(stage_recipe.clip_frames)
        return train["joints"][index[:, None].to(device), frames.to(device)]

    def train_step(stage):
        count, size = len(train["joints"]), stage_recipe.batch_size
        index = stage.batch(count, size)
        joints = clips(index, stage.generator)
        noise = source_noise(joints.shape, stage_recipe, stage.generator).to(device)
        target = bodies[torch.randint(len(bodies), (size,), generator=stage.generator)]
        loss, terms, joints_ab = smrm_losses(
            model, discriminator, joints, joints + noise,
            train["tpose_joints"][index], target, stage_recipe)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        real = clips(stage.batch(count, size), stage.generator)
        loss_d = discriminator_loss(discriminator, real, joints_ab)
        optimizer_d.zero_grad(set_to_none=True)
        loss_d.backward()
        optimizer_d.step()
        return {"loss": loss.item(), **terms, "discriminator": loss_d.item()}

    # Validation: each clip onto the next validation body, against the Mixamo ground truth.
    val_bodies = val["bodies_tpose_joints"]

    # And with the training noise on the source (fixed draws), as the runtime's SKR gives it.
    val_count = min(VALIDATION_LIMIT, len(val["joints"]))
    val_noise = source_noise(val["joints"][:val_count].shape, stage_recipe,
                             torch.Generator().manual_seed(recipe.seed)).to(device)

    def evaluate():
        def errors(index):
            target = val_bodies[(val["body"][index].long() + 1) % len(val_bodies)]
            truth = retarget_ground_truth(val["rotations"][index], val["root"][index],
                                          val["tpose_joints"][index], target)
            _, _, joints, _ = model(val["joints"][index], target)
            _, _, noisy, _ = model(val["joints"][index] + val_noise[index], target)
            local = lambda x: x - x[:, :, :1]  # noqa: E731
            return {"val_mpjpe": float((joints - truth).norm(dim=-1).mean()),
                    "val_mpjpe_root_relative": float(
                        (local(joints) - local(truth)).norm(dim=-1).mean()),
                    "val_mpjpe_noisy_source": float((noisy - truth).norm(dim=-1).mean())}
        return mean_over_batches(val_count, 128, errors)

    return model, stage.run(train_step, evaluate, resume, limit)


# ----------------------------------------------------------------------------- command line

def current_commit():
    """The repository's HEAD commit, with "+modified" if tracked files differ from it, or
    "unknown" outside a git checkout."""
    def git(*args):
        return subprocess.run(["git", *args], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    try:
        return git("rev-parse", "HEAD") + ("+modified" if git("status", "--porcelain",
                                                              "--untracked-files=no") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


# The built datasets each stage reads from --data (``_train`` and ``_val`` of each).
STAGE_DATA = {"skr": ("skr", "skr_tpose"), "refine": ("skr", "skr_tpose"),
              "denoise": ("sequences",), "skin": ("skin",), "smrm": ("smrm",)}


def missing_data(data_dir, stages, pack=None):
    """The dataset files ``stages`` need that ``data_dir`` lacks (SKR with a pack reads only
    the T-pose frames there), so that a long run does not die at its third stage."""
    needed = {f"{name}_{split}.npz" for stage in stages for name in STAGE_DATA[stage]
              if not (stage == "skr" and pack is not None and name == "skr")
              for split in ("train", "val")}
    return sorted(name for name in needed if not (Path(data_dir) / name).is_file())


RUN_FILES = tuple(f"{stage}.{kind}" for stage in STAGES for kind in ("pt", "csv", "png")) + (
    "recipe.json", "init.json", "weights.npz")
RESUMABLE_CHANGES = ("steps", "eval_every")   # a resumed stage may be extended


def earlier_run(run_dir):
    """The names of an earlier run's files in ``run_dir`` (``RUN_FILES``)."""
    return [name for name in RUN_FILES if (Path(run_dir) / name).is_file()]


def _flat(values, prefix=""):
    for key, value in values.items():
        if isinstance(value, dict):
            yield from _flat(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def resume_differences(run_dir, settings):
    """What ``settings`` ({"recipe": ..., "init_sha256": ...}, as ``main`` makes them)
    change from the ones the run in ``run_dir`` was started with, a list of "key: then,
    now" strings. Only what the run recorded counts (an older run lacks later fields, whose
    defaults it used, and may lack init.json), and of the stages' sections only those of
    stages with a checkpoint there (a stage not started yet, or whose files were deleted to
    train it again, takes this run's); the steps and evaluation spacing may change."""
    then = {}
    for name, key in (("recipe.json", "recipe"), ("init.json", "init_sha256")):
        path = Path(run_dir) / name
        if path.is_file():
            then[key] = json.loads(path.read_text())
    then, now = dict(_flat(then)), dict(_flat(settings))
    unstarted = {f"recipe.{stage}." for stage in STAGES
                 if not (Path(run_dir) / f"{stage}.pt").is_file()}
    return [f"{key}: {then[key]} then, {now.get(key)} now" for key in sorted(then)
            if then[key] != now.get(key) and key.rsplit(".", 1)[-1] not in RESUMABLE_CHANGES
            and not any(key.startswith(prefix) for prefix in unstarted)]


LEARNERS = {"skr": ("refine", "denoise"), "refine": ("denoise",)}   # learn from its output


def check_learners(run_dir, recipe):
    """ValueError if a stage in ``run_dir`` is to train further (more steps than it ran)
    while a stage that learns from its output has a checkpoint: that one would keep what
    it learned from the old output."""
    for stage, learners in LEARNERS.items():
        path = Path(run_dir) / f"{stage}.pt"
        stale = [name for name in learners if (Path(run_dir) / f"{name}.pt").is_file()]
        if not (stale and path.is_file()):
            continue
        state = read_checkpoint(path)
        steps = state["steps"] if state.get("planned") else getattr(recipe, stage).steps
        if state["step"] < steps:
            raise ValueError(f"--resume: {stage} goes on from step {state['step']} to {steps}, "
                             f"but {' and '.join(stale)} learned its output so far: delete "
                             f"{', '.join(f'{name}.*' for name in stale)} in {run_dir} to "
                             "train them again on it")


def provenance(recipe, data_dir, init=None, pack=None, online=ONLINE_FRAMES):
    """What made these weights: recipe, data manifest summary (and the data pack SKR drew
    from, if any), commit, and the provenance of the weights training started from, if any."""
    commit = current_commit()
    manifest_path = Path(data_dir) / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.exists() else {}
    out = {"recipe": json.loads(recipe.to_json()), "commit": commit,
           "data": {k: manifest.get(k) for k in ("config", "counts", "actor_hip_height")}}
    if pack is not None:
        out["data"]["skr_online_pack"] = {
            "sha256": pack.sha256,
            "motions": {split: len(pack.motions[split]) for split in ("train", "val")},
            "bodies": {split: len(pack.bodies[split]) for split in ("train", "val")},
            "include_broken": pack.include_broken,
            "keep_broken_ankles": pack.keep_broken_ankles,
            "config": dataclasses.asdict(online)}
    if init is not None:
        out["init"] = init.metadata
    return out


def stage_list(text):
    """"all" or "skr,smrm" -> the stages in training order."""
    names = STAGES if text == "all" else tuple(text.split(","))
    unknown = [n for n in names if n not in STAGES]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown stage {unknown}: choose from {STAGES} "
                                         "or all")
    return tuple(n for n in STAGES if n in names)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m training.train",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("stage", type=stage_list,
                        help="skr, refine, denoise, skin, smrm, a comma-separated list of "
                             "them, or all")
    parser.add_argument("--recipe", required=True,
                        help="a recipe JSON file, or the name of one in training/recipes")
    parser.add_argument("--data", default="data", help="the directory of the built datasets")
    parser.add_argument("--out", required=True, help="the run directory")
    again = parser.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the run in --out from its checkpoints, with the same "
                            "recipe, --init and data (more steps allowed)")
    again.add_argument("--overwrite", action="store_true",
                       help="delete an earlier run's files in --out first (checkpoints, "
                            "logs, weights.npz)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                        help="cpu, cuda or cuda:N (default: cuda when there is one)")
    parser.add_argument("--threads", type=int_at_least(1), help="torch CPU threads")
    parser.add_argument("--init", metavar="WEIGHTS",
                        help="start from an exported weights file (e.g. the shipped one) "
                             "instead of random initialisation; stages not trained keep it")
    parser.add_argument("--scratch", type=stage_list, default=(), metavar="STAGES",
                        help="with --init: these stages start from random initialisation "
                             "(e.g. smrm, to retrain it alone for an ablation)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value (JSON), e.g. smrm.clip_frames=10; "
                             "repeatable")
    parser.add_argument("--stop-at", type=int_at_least(1), metavar="STEP",
                        help="stop each stage at this step, checkpointed, to --resume later")
    parser.add_argument("--stage-seconds", type=positive_float, metavar="S",
                        help="train each stage for at most S seconds of wall clock (its "
                             "loop; not the data it prepares first): its steps are cut to "
                             "what fits, timed as it runs, and its learning-rate schedule "
                             "still ends (a run on a lent GPU)")
    parser.add_argument("--pack", metavar="FILE",
                        help="SKR draws fresh frames every batch from this data pack "
                             "(python -m training.data pack) and validates on "
                             f"{VALIDATION_LIMIT:,} drawn once from its validation split; "
                             "--data still gives the T-pose frames (skr_tpose_*.npz)")
    parser.add_argument("--online", action="append", default=[], metavar="KEY=VALUE",
                        help="with --pack: draw SKR's training frames with this build option "
                             f"changed ({', '.join(ONLINE_FIELDS)}; e.g. crossed_fraction=0.15), "
                             "validation's as ever; repeatable")
    args = parser.parse_args(argv)
    pack = None
    if args.pack is not None:
        try:
            pack = without_broken_ankles(load_pack(args.pack))   # as builds cut them
        except ValueError as error:
            parser.error(f"--pack: {error}")
    if args.online and pack is None:
        parser.error("--online changes the frames drawn from a pack: give --pack")
    try:
        online = online_config(args.online)
    except ValueError as error:
        parser.error(f"--online: {error}")
    if args.scratch and not args.init:
        parser.error("--scratch: the stages not retrained come from --init: give it")
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as error:
        parser.error(f"--device {args.device}: {error}")
    if args.threads:
        torch.set_num_threads(args.threads)
    recipe = load_recipe(args.recipe, args.set)
    init = load_weights(args.init) if args.init else None
    if init is not None and init.config.rest_pose:     # fitted, not trained: carried along
        if recipe.model.smrm_analytic_prior:
            recipe = dataclasses.replace(recipe, model=dataclasses.replace(recipe.model,
                                                                           rest_pose=True))
        else:
            print("note: the --init weights' rest-pose model is left out: this recipe's SMRM "
                  "has no analytic prior for it to move")
            init = init._replace(config=dataclasses.replace(init.config, rest_pose=False),
                                 rest_pose=None)
    run_dir = Path(args.out)
    earlier = earlier_run(run_dir)
    settings = {"recipe": json.loads(recipe.to_json()),
                "init_sha256": file_sha256(args.init) if args.init else None}
    if earlier and not (args.resume or args.overwrite):
        raise ValueError(f"{run_dir}: holds an earlier run ({', '.join(earlier[:4])}"
                         f"{', ...' if len(earlier) > 4 else ''}): add --resume to continue "
                         "it, or --overwrite to start again")
    if earlier and args.resume:
        changed = resume_differences(run_dir, settings)
        if changed:
            raise ValueError(f"--resume: {run_dir} was started with other settings ("
                             f"{'; '.join(changed)}): resume with the same, delete a stage's "
                             f"files there (<stage>.pt, .csv, .png) to train it again with "
                             "this recipe, or start again with --overwrite")
        check_learners(run_dir, recipe)
    # The recipe's own stages: refine and denoise only if its model has them.
    optional = {"refine": recipe.model.refines, "denoise": recipe.model.denoises}
    own = tuple(n for n in STAGES if optional.get(n, True))
    stages = tuple(n for n in args.stage if n in own)
    if pack is not None and "skr" not in stages:
        parser.error("--pack: only the skr stage draws from a pack, and it is not trained here")
    missing = missing_data(args.data, stages, pack)
    if missing:
        raise ValueError(f"{args.data}: lacks {', '.join(missing)}: build the data first "
                         "(python -m training.data build --out DIR)")

    def trained(name):
        """Whether the refiner or denoiser is trained here or loaded from --init: one that
        is neither is random, so it is never exported nor learned from."""
        return optional[name] and (name in stages or (
            init is not None and getattr(init, name) is not None
            and name not in args.scratch))
    trainers = {"skr": lambda *a: train_skr(*a, pack=pack, online=online), "skin": train_skin,
                "smrm": train_smrm,
                "refine": lambda *a: train_refine(*a, skr=models["skr"]),
                "denoise": lambda *a: train_denoise(*a, skr=models["skr"], refine=models[
                    "refine"] if trained("refine") else None)}
    if not stages:
        parser.error("the recipe's model has no refiner (model.refine_point_widths) or no "
                     "denoiser (model.denoise_hidden)")
    for name, what in (("refine", "refiner"), ("denoise", "denoiser")):
        if name in stages and "skr" not in stages and init is None:
            parser.error(f"the {what} learns a trained SKR's errors: train skr with it "
                         f"(skr,{name}) or start from a trained SKR (--init WEIGHTS)")
        if ("skr" in stages and name not in stages and init is not None
                and getattr(init, name) is not None):
            print(f"warning: SKR is retrained but not the {what}, which learned the old "
                  f"SKR's errors; train skr,{name} to retrain both")
    if "refine" in stages and "denoise" not in stages and init is not None \
            and init.denoise is not None:
        print("warning: the refiner is retrained but not the denoiser, which learned the old "
              "refiner's errors; train refine,denoise to retrain both")
    torch.manual_seed(recipe.seed)
    models, finished = initial_models(recipe, init, args.scratch), True
    limit = Limit(args.stop_at, args.stage_seconds)
    if args.overwrite:
        for name in earlier:
            (run_dir / name).unlink()
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, value in (("recipe.json", recipe.to_json()),
                        ("init.json", json.dumps(settings["init_sha256"]))):
        with atomic_write(run_dir / name) as file:
            file.write(value.encode())
    for name in stages:
        start = time.perf_counter()
        try:
            models[name], finished = trainers[name](recipe, args.data, run_dir, args.device,
                                                    args.resume, limit, models[name])
        except ResumeMismatch as error:
            parser.error(f"--resume: {error}")
        print(f"{name}: {time.perf_counter() - start:.0f} s{'' if finished else ' (stopped)'}")
        if not finished:    # the stages after it may learn from it: they wait for --resume
            break
    if finished and (stages == own or init is not None):
        path = run_dir / "weights.npz"
        export_weights(path, models["skr"].cpu(), models["smrm"].cpu(), models["skin"].cpu(),
                       metadata=provenance(recipe, args.data, init, pack, online),
                       refine=models["refine"].cpu() if trained("refine") else None,
                       denoise=models["denoise"].cpu() if trained("denoise") else None,
                       skr_view=None if init is None else init.skr_view)   # trained apart
        print(f"exported {path}")
    elif finished:
        print(f"not exported: the stages not trained here ({', '.join(set(own) - set(stages))}) "
              "have no weights; give --init WEIGHTS to carry them")


def run_command(argv=None):
    """``main`` for the command line: bad input is one line naming it (exit status 1), not a
    traceback; an interrupt says what is kept (130)."""
    try:
        main(argv)
    except (ValueError, OSError) as error:
        print(f"python -m training.train: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("python -m training.train: interrupted; each stage's checkpoint is kept: add "
              "--resume to continue", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(run_command())
