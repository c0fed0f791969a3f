"""``avoid-train train``: PPO on the simulator with stacked scans, held-out evaluation and checkpoints.

Read top to bottom: the environments (all simulators batched in this process, or one per
process with ``vec_env = "subproc"``; monitored, 4 scans stacked —
the same stacking the companion's FrameStack does in flight), the callbacks (checkpoints, the
held-out evaluation that logs success rate and drives the curriculum), the model, ``learn``.

A run lives in ``<run_root>/<config name>-s<seed>/``::

    config.toml            the resolved config (export and evaluate read it)
    checkpoints/ppo_<steps>_steps.zip
    checkpoints/dagger_<steps>_steps.zip   the student after each DAgger iteration
    dagger/iteration_<k>.npz               that iteration's labels (``--resume`` goes on from them)
    tb/                    TensorBoard logs (``tensorboard --logdir runs``)
    eval.csv               one row per evaluation: steps, wall-clock seconds, difficulty, success rate
                           (also on the worlds with movers alone)...
    best_model.zip         best evaluation at the target difficulty
    eval_model.zip         the model the last held-out evaluation flew (overwritten at each one)
    final_model.zip
    interrupted.zip        the model at the moment of a Ctrl-C (``--resume`` picks it up)

A directory that already holds a run is never reused silently: ``--resume`` continues it from its
newest checkpoint, ``--overwrite`` deletes it first, and anything else is refused.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import fcntl
import functools
import json
import logging
import math
import multiprocessing
import os
import shutil
import signal
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from companion.common.errors import UserError
from companion.perception.scan import N_BINS
from flightsim.worlds.families import DYNAMIC_FAMILIES
from training.config import TrainConfig, config_to_toml, load_train_config, observation_layout
from training.controllers import ControllerSpec
from training.episodes import WorldSpec, goal_worlds, make_tasks
from training.evaluate import run_tasks
from training.mirror import Mirror, mirror_for
from training.progress import Progress
from training.report import summarise
from training.vec_env import ignore_sigint_in_worker, make_vec_env

log = logging.getLogger(__name__)

EVAL_FIELDS = (
    "timesteps",
    "wall_s",
    "difficulty",
    "success_rate",
    "mean_distance_m",
    "collisions",
    "episodes",
    "moving_success_rate",
)


def read_eval_log(path: Path) -> list[dict[str, float]]:
    """The rows of a run's ``eval.csv`` (empty when there is none yet)."""
    if not path.is_file():
        return []
    with path.open() as f:
        # a field left empty (moving_success_rate without movers) or absent (an older run's) is nan
        return [{k: float(v or "nan") for k, v in row.items()} for row in csv.DictReader(f)]


def write_eval_log(path: Path, rows: list[dict[str, float]]) -> None:
    """Rewrite ``eval.csv`` with ``rows`` (a resume drops the rows of the abandoned continuation)."""
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=EVAL_FIELDS)
        writer.writeheader()
        for row in rows:
            writer.writerow(
                {
                    k: int(v) if k in ("timesteps", "collisions", "episodes") else "" if math.isnan(v) else v
                    for k, v in row.items()
                }
            )


def checkpoint_steps(path: Path) -> int:
    """The step count saved in an SB3 model zip (its ``data`` JSON), without loading torch."""
    try:
        with zipfile.ZipFile(path) as z:
            return int(json.loads(z.read("data"))["num_timesteps"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path}: not a stable-baselines3 model ({exc})") from None


def save_atomically(model: Any, path: Path) -> None:
    """``model.save(path)`` under a temporary name, then renamed: a kill during the save leaves no
    cut-off zip under a model's name (a checkpoint ``--resume`` would pick as the newest, the
    ``best_model.zip`` the run chose). A Ctrl-C waits for the save to end (:func:`sigint_deferred`).
    Every model the run writes goes through it."""
    partial = path.with_name(f".partial-{path.name}")
    try:
        with sigint_deferred():
            model.save(partial)
            os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) that arrives inside the block until it ends, then act on it as the
    handler before would have. A KeyboardInterrupt inside torch's zip writer left it raising
    ``RuntimeError: unexpected pos`` instead, so the run died with a traceback and exit 1, not
    ``interrupted.zip`` and 130. Only the main thread receives signals; elsewhere, or where
    SIGINT is ignored (the simulator workers), the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN or previous is None:
        yield
        return
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, _frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        if callable(previous):
            previous(signal.SIGINT, None)  # Python's default handler raises KeyboardInterrupt
        else:
            signal.raise_signal(signal.SIGINT)  # SIG_DFL: as if it arrived now


def latest_checkpoint(run_dir: Path) -> Path:
    """The checkpoint of ``run_dir`` with the most steps: ``checkpoints/ppo_<N>_steps.zip`` or
    ``interrupted.zip``; before any PPO step, the last DAgger iteration's
    ``checkpoints/dagger_<N>_steps.zip``."""
    candidates = [*sorted((run_dir / "checkpoints").glob("ppo_*_steps.zip"))]
    if not candidates:
        candidates = [*sorted((run_dir / "checkpoints").glob("dagger_*_steps.zip"))]
    if (run_dir / "interrupted.zip").is_file():
        candidates.append(run_dir / "interrupted.zip")
    if not candidates:
        raise UserError(f"--resume: {run_dir} has no checkpoint to continue from")
    return max(candidates, key=checkpoint_steps)


def prepare_run_dir(config: TrainConfig, resume: bool, overwrite: bool) -> None:
    """Refuse to reuse a run directory unless told how: ``resume`` it or ``overwrite`` it."""
    run_dir = config.run_dir
    used = run_dir.is_dir() and any(run_dir.iterdir())
    if used and overwrite:
        log.info("--overwrite: deleting the previous run in %s", run_dir)
        shutil.rmtree(run_dir)
    elif used and not resume:
        raise UserError(
            f"{run_dir} already holds a run: --resume to continue it, --overwrite to replace it, "
            "or choose another name, seed or run_root"
        )


@contextlib.contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold ``.<run name>.lock`` beside the run directory while a run writes in it, and refuse a
    second run of the same directory while the first is alive.

    The lock file sits in the run root, not in the run directory, so it still stands when the
    directory is deleted under a live run; the kernel releases it when the process ends, however it
    ends, so a killed run leaves nothing to clean up.
    """
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    path = run_dir.parent / f".{run_dir.name}.lock"
    with path.open("a+") as held:
        try:
            fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            held.seek(0)
            owner = held.read().strip() or "unknown"
            raise UserError(
                f"{run_dir} is in use by another training run (pid {owner}): wait for it to end or stop it"
            ) from None
        held.truncate(0)
        held.write(str(os.getpid()))
        held.flush()
        yield


def truncate_eval_log(run_dir: Path, steps: int, target_difficulty: float) -> None:
    """Keep only the evaluations up to the resumed checkpoint's ``steps``.

    Rows after it belong to a continuation the resume abandons: the timesteps would run backwards
    and the best model would be judged against a future that no longer exists. If the current
    ``best_model.zip`` came from such a row it is deleted too, so the resumed run judges anew.
    """
    path = run_dir / "eval.csv"
    rows = read_eval_log(path)
    kept = [r for r in rows if r["timesteps"] <= steps]
    if len(kept) == len(rows):
        return
    dropped = rows[len(kept) :]
    log.info("--resume at %d steps: dropping %d later evaluation(s) from %s", steps, len(dropped), path)
    write_eval_log(path, kept)

    def best(rs: list[dict[str, float]]) -> float:
        return max(
            (r["success_rate"] for r in rs if r["difficulty"] >= target_difficulty - 1e-9), default=-1.0
        )

    if best(dropped) > -1.0 and best(dropped) >= best(kept):
        (run_dir / "best_model.zip").unlink(missing_ok=True)


def make_callbacks(config: TrainConfig, run_dir: Path, n_envs: int, executor: Any, start_difficulty: float):
    """Checkpoints every ``checkpoint_every`` steps and the held-out evaluation (+ curriculum)."""
    from stable_baselines3.common.callbacks import BaseCallback

    # the held-out worlds are flown behind the companion's shield, as on the drone, and without it:
    # a policy that needs the shield to stay clear is not the best, however fast it flies behind it
    eval_envs = [
        (" behind the shield", {**config.env, "shield": True, "unshielded_fraction": 0.0}),
        (" without it", {**config.env, "shield": False}),
    ]

    class HeldOutEvaluation(BaseCallback):
        """Every ``eval.every_steps``: fly ``eval.n_worlds`` held-out worlds, log success, set difficulty.

        The worlds are flown with and without the shield and the logged success rate is the lower
        of the two (distance: their mean; collisions: their sum).
        """

        def __init__(self) -> None:
            super().__init__()
            self.difficulty = start_difficulty
            self.log_path = run_dir / "eval.csv"
            previous = read_eval_log(self.log_path)
            self.wall_offset = previous[-1]["wall_s"] if previous else 0.0
            # judged against the best model on disk: none (a new run, or a resume dropped it) → any
            self.best = (
                max((r["success_rate"] for r in previous if self._at_target(r["difficulty"])), default=-1.0)
                if (run_dir / "best_model.zip").is_file()
                else -1.0
            )
            self.started = time.monotonic()
            self.last_eval = 0

        def _at_target(self, difficulty: float) -> bool:
            return difficulty >= config.eval.difficulty - 1e-9

        def _on_training_start(self) -> None:
            self.last_eval = self.num_timesteps

        def _on_step(self) -> bool:
            if self.num_timesteps - self.last_eval >= config.eval.every_steps:
                self.last_eval = self.num_timesteps
                self.evaluate()
            return True

        def _on_training_end(self) -> None:
            if self.num_timesteps > self.last_eval:
                self.evaluate()

        def evaluate(self) -> None:
            model_path = run_dir / "eval_model.zip"
            save_atomically(self.model, model_path)
            difficulty = self.difficulty if config.curriculum.enabled else config.eval.difficulty
            seeds = range(config.eval.first_seed, config.eval.first_seed + config.eval.n_worlds)
            if not config.is_goal_task:
                worlds = [WorldSpec(f"seed-{s}", seed=s, difficulty=difficulty) for s in seeds]
            else:  # n_worlds validation worlds per family
                env_config = config.env_config()
                worlds = goal_worlds(
                    env_config.families,
                    config.eval.first_seed,
                    config.eval.n_worlds,
                    env_config.difficulty_range,
                )
            policy = [ControllerSpec("policy", str(model_path))]
            modes, moving = {}, {}
            # logged, not a bar: PPO's own bar may be on the terminal
            what = f"eval at {self.num_timesteps} steps: episodes"
            with Progress(len(worlds) * len(eval_envs), what, "episode", bar=False) as progress:
                for name, env in eval_envs:
                    tasks = make_tasks(policy, worlds, 1, env, config.env_id)
                    results = run_tasks(tasks, executor, progress)
                    modes[name] = summarise(results)
                    with_movers = [r for r in results if r.family in DYNAMIC_FAMILIES]
                    if with_movers:
                        moving[name] = summarise(with_movers)
            row = {
                "timesteps": self.num_timesteps,
                "wall_s": round(self.wall_offset + time.monotonic() - self.started, 1),
                "difficulty": difficulty,
                # a policy is only as good as its worse way of flying
                "success_rate": min(m["success_rate"] for m in modes.values()),
                "mean_distance_m": float(np.mean([m["mean_distance_m"] for m in modes.values()])),
                "collisions": sum(m["collisions"] for m in modes.values()),
                "episodes": sum(m["episodes"] for m in modes.values()),
                # the same on the worlds with movers alone, which the figure over all families hides
                "moving_success_rate": min((m["success_rate"] for m in moving.values()), default=math.nan),
            }
            for key in ("success_rate", "mean_distance_m", "collisions", "difficulty", "moving_success_rate"):
                self.logger.record(f"eval/{key}", row[key])
            write_eval_log(self.log_path, [*read_eval_log(self.log_path), row])
            for name, m in modes.items():
                log.info(
                    "eval at %d steps (%.0f s)%s: difficulty %.2f success %.0f%% distance %.1f m "
                    "collisions %d/%d",
                    row["timesteps"],
                    row["wall_s"],
                    name,
                    difficulty,
                    100 * m["success_rate"],
                    m["mean_distance_m"],
                    m["collisions"],
                    m["episodes"],
                )
                if name in moving:
                    log.info(
                        "eval%s, the worlds with movers: success %.0f%% of %d",
                        name,
                        100 * moving[name]["success_rate"],
                        moving[name]["episodes"],
                    )
            if self._at_target(difficulty) and row["success_rate"] >= self.best:
                self.best = row["success_rate"]
                save_atomically(self.model, run_dir / "best_model.zip")
            self.advance_curriculum(row["success_rate"])

        def advance_curriculum(self, success_rate: float) -> None:
            c = config.curriculum
            target = config.eval.difficulty
            if not c.enabled or success_rate < c.threshold or self.difficulty >= target:
                return
            self.difficulty = min(target, self.difficulty + c.step)
            self.training_env.env_method("set_difficulty", self.difficulty)
            log.info("curriculum: training difficulty now %.2f", self.difficulty)

    checkpoints = atomic_checkpoint_callback()(
        save_freq=max(config.checkpoint_every // n_envs, 1),
        save_path=str(run_dir / "checkpoints"),
        name_prefix="ppo",
    )
    return [checkpoints, HeldOutEvaluation()]


def atomic_checkpoint_callback() -> type:
    """SB3's :class:`CheckpointCallback` writing each ``ppo_<N>_steps.zip`` with
    :func:`save_atomically` (a Ctrl-C mid-save once left a cut-off one, and ``--resume`` failed on it)."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    class AtomicCheckpointCallback(CheckpointCallback):
        def _on_step(self) -> bool:
            if self.n_calls % self.save_freq == 0:
                save_atomically(self.model, Path(self._checkpoint_path(extension="zip")))
            return True

    return AtomicCheckpointCallback


def policy_kwargs(config: TrainConfig) -> dict[str, Any]:
    """SB3's ``policy_kwargs`` for the config's network."""
    p = config.ppo
    kwargs: dict[str, Any] = {
        "net_arch": {"pi": list(p.net_arch), "vf": list(p.net_arch)},
        "log_std_init": p.log_std_init,
    }
    if p.features_extractor == "circular_scan":
        from training.scan_features import CircularScanExtractor

        kwargs |= {
            "features_extractor_class": CircularScanExtractor,
            "features_extractor_kwargs": {"n_stack": config.n_stack, "n_bins": N_BINS}
            | ({"layers": tuple(p.scan_layers)} if p.scan_layers else {})
            | (_mover_ring_kwargs(config) if p.mover_ring else {}),
            "share_features_extractor": False,  # the critic's returns would swamp the actor's features
        }
    return kwargs


def _mover_ring_kwargs(config: TrainConfig) -> dict[str, Any]:
    """The circular extractor's ``movers_at`` (from the env's layout) and ``mover_times``."""
    layout = observation_layout(config.env_config())
    return {"movers_at": layout.slices()["movers"].start, "mover_times": tuple(config.ppo.mover_ring)}


def build_model(config: TrainConfig, venv: Any, run_dir: Path, resume: Path | None):
    """A fresh PPO model from the config, or the checkpoint ``resume`` attached to ``venv``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.utils import LinearSchedule

    if resume is not None:
        from training.export import load_model

        load_model(resume)  # a bad file is the user's error, reported in one line
        return PPO.load(str(resume), env=venv, device="cpu", tensorboard_log=str(run_dir / "tb"))
    p = config.ppo
    linear = p.learning_rate_schedule == "linear"
    model = PPO(
        "MlpPolicy",
        venv,
        learning_rate=LinearSchedule(p.learning_rate, 0.0, 1.0) if linear else p.learning_rate,
        n_steps=p.n_steps,
        batch_size=p.batch_size,
        n_epochs=p.n_epochs,
        gamma=p.gamma,
        gae_lambda=p.gae_lambda,
        clip_range=p.clip_range,
        ent_coef=p.ent_coef,
        vf_coef=p.vf_coef,
        max_grad_norm=p.max_grad_norm,
        policy_kwargs=policy_kwargs(config),
        tensorboard_log=str(run_dir / "tb"),
        seed=config.seed,
        device="cpu",
        verbose=1,
        target_kl=p.target_kl or None,
    )
    if p.init_from:
        start_from(model, Path(p.init_from), p.log_std_init)
    return model


def start_from(model: Any, path: Path, log_std: float) -> None:
    """Give ``model`` the actor and critic weights of the trained model ``path`` (a fine-tune).

    Only the network's weights are taken: the optimizer restarts, the hyperparameters stay the
    config's, and the action noise restarts at ``log_std`` (a DAgger student never fitted its own).

    :raises UserError: ``path`` is not a checkpoint, or its network is not this config's
    """
    import torch

    trained = initial_model(path).policy.state_dict()
    try:
        model.policy.load_state_dict(trained)
    except RuntimeError as exc:
        # torch: "Error(s) in loading state_dict for ...:" then one line per mismatch; name the first
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 else " ".join(lines)
        raise UserError(f"ppo.init_from {path}: its network is not this config's ({detail})") from None
    with torch.no_grad():
        model.policy.log_std.fill_(log_std)


def initial_model(path: Path) -> Any:
    """The model ``ppo.init_from`` names, loaded.

    :raises UserError: naming ``ppo.init_from``, when ``path`` is missing or not an SB3 checkpoint
    """
    from training.export import load_model

    try:
        return load_model(path)
    except UserError as exc:
        raise UserError(f"ppo.init_from: {exc}") from None


def dagger_steps(config: TrainConfig) -> int:
    """Env steps each DAgger iteration collects: ``pretrain.steps``, or with ``total_timesteps``
    set, at most an even share of it, so that a short run is short (``total_timesteps`` counts
    DAgger's steps; PPO gets what is left)."""
    p = config.pretrain
    if not config.total_timesteps:
        return p.steps
    return max(1, min(p.steps, config.total_timesteps // p.iterations))


def warm_start(
    config: TrainConfig, venv: Any, model: Any, evaluation: Any, resume: Path | None = None
) -> int:
    """Imitation before PPO: behaviour cloning of a classical controller (:mod:`training.pretrain`)
    or DAgger from the privileged teacher (:mod:`training.dagger`), each fitting the fresh
    model's actor and critic. DAgger saves each iteration (its labels in ``dagger/``, the student
    as ``checkpoints/dagger_<steps>_steps.zip``) and runs the held-out evaluation after it.

    :param evaluation: the run's ``HeldOutEvaluation`` callback
    :param resume: a DAgger checkpoint of this run: go on after its iteration, on its labels
    :return: the env steps DAgger collected, which count in ``total_timesteps`` (behaviour
        cloning's do not: 0)
    """
    from training import pretrain

    p = config.pretrain
    if p.method == "dagger":
        from stable_baselines3.common.logger import configure

        from training import dagger

        run_dir = config.run_dir
        previous = dagger.load_iterations(run_dir / "dagger", checkpoint_steps(resume)) if resume else []
        if len(previous) >= p.iterations:
            raise UserError(
                f"--resume: {resume} has {len(previous)} DAgger iterations, pretrain.iterations is "
                f"{p.iterations}: raise it to go on"
            )

        def after(iteration: int, collected: int, rollouts: dagger.Rollouts) -> None:
            dagger.save_iteration(run_dir / "dagger", iteration, rollouts)
            model.num_timesteps = collected
            (run_dir / "checkpoints").mkdir(exist_ok=True)
            save_atomically(model, run_dir / "checkpoints" / f"dagger_{collected}_steps.zip")
            evaluation.num_timesteps = collected  # imitation steps mark the evaluation log's rows
            evaluation.evaluate()
            model.logger.dump(collected)

        # learn sets up the logger; before it, the evaluation logs to a run-wide one (kept after)
        model.set_logger(configure(str(run_dir / "tb" / "dagger"), ["stdout", "csv", "tensorboard"]))
        evaluation.init_callback(model)
        data = dagger.run(
            venv, model, iterations=p.iterations, steps=dagger_steps(config), beta0=p.beta0,
            epochs=p.epochs, batch_size=p.batch_size, learning_rate=p.learning_rate, seed=config.seed,
            previous=previous, after_iteration=after, teacher=p.teacher, teacher_noise=p.teacher_noise,
            schedule=p.learning_rate_schedule, weigh=label_weights(config), mirror=label_mirror(config),
            bar=config.progress_bar,
        )  # fmt: skip
        return len(data.actions)
    data = pretrain.collect(
        venv, config.n_stack, p.demonstrator, config.env_config(), p.steps, config.ppo.gamma,
        bar=config.progress_bar,
    )  # fmt: skip
    log.info(
        "warm start: %d steps of %s, %d episodes ended, %d of them successes",
        len(data.actions), p.demonstrator, data.episodes, data.successes,
    )  # fmt: skip
    pretrain.fit(
        model.policy, data, p.epochs, p.batch_size, p.learning_rate, config.seed, p.learning_rate_schedule,
        mirror=label_mirror(config),
    )  # fmt: skip
    return 0


def label_weights(config: TrainConfig) -> Callable[[np.ndarray], np.ndarray] | None:
    """DAgger's label weights (``[pretrain] near_weight``), or None when it is 0."""
    from training.pretrain import proximity_weights

    p, scan = config.pretrain, config.env_config().scan
    if p.near_weight == 0.0:
        return None
    return functools.partial(
        proximity_weights, n_stack=config.n_stack, n_bins=N_BINS, max_range=scan.max_range,
        near_weight=p.near_weight, near_distance=p.near_distance,
    )  # fmt: skip


def label_mirror(config: TrainConfig) -> Mirror | None:
    """How the fits mirror their demonstrations (``[pretrain] mirror``), or None when they do not."""
    if not config.pretrain.mirror:
        return None
    env_config = config.env_config()
    return mirror_for(observation_layout(env_config), config.n_stack, getattr(env_config, "sideways", False))


class TrainingInterrupted(Exception):
    """Ctrl-C during ``learn``: the model was saved as ``path`` after ``steps`` steps."""

    def __init__(self, path: Path, steps: int) -> None:
        super().__init__(f"interrupted after {steps} steps; saved {path} (continue with --resume)")
        self.path = path
        self.steps = steps


def train(config: TrainConfig, resume: Path | None = None) -> Path:
    """Run (or resume) training; returns the final model's path.

    :param config: the checked training config
    :param resume: an SB3 checkpoint of this run to continue from (timesteps continue its count)
    :raises TrainingInterrupted: Ctrl-C; the model at that moment is in ``interrupted.zip``
    """
    import torch

    torch.set_num_threads(1)  # the cores belong to the simulators; a 1440-64-64 MLP needs no more
    run_dir = config.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.toml").write_text(config_to_toml(config))
    n_envs = config.resolved_n_envs
    if resume:
        truncate_eval_log(run_dir, checkpoint_steps(resume), config.eval.difficulty)
    previous = read_eval_log(run_dir / "eval.csv") if resume else []
    difficulty = config.env_config().difficulty
    if config.curriculum.enabled:
        difficulty = previous[-1]["difficulty"] if previous else config.curriculum.start_difficulty
    venv = make_vec_env(config, n_envs, config.seed, difficulty=difficulty)
    eval_workers = config.eval.workers or n_envs
    executor = (
        ProcessPoolExecutor(
            eval_workers,
            mp_context=multiprocessing.get_context("forkserver"),
            initializer=ignore_sigint_in_worker,
        )
        if eval_workers > 1
        else None
    )
    try:
        model = build_model(config, venv, run_dir, resume)
        callbacks = make_callbacks(config, run_dir, n_envs, executor, difficulty)
        in_dagger = resume is not None and resume.name.startswith("dagger_")
        imitated = 0  # DAgger's env steps, counted in total_timesteps
        if config.pretrain.steps and (resume is None or in_dagger):
            imitated = warm_start(config, venv, model, callbacks[-1], resume)
            if config.total_timesteps <= imitated:
                final = run_dir / "final_model.zip"
                save_atomically(model, final)
                return final
        continued = resume is not None and not in_dagger  # PPO steps already taken
        remaining = config.total_timesteps - (model.num_timesteps if continued else imitated)
        if remaining <= 0:
            raise UserError(f"{resume} already has {model.num_timesteps} steps >= total_timesteps")
        log.info(
            "training %s: %d steps on %d envs, run directory %s", config.name, remaining, n_envs, run_dir
        )
        try:
            model.learn(
                total_timesteps=remaining,
                callback=callbacks,
                progress_bar=config.progress_bar,
                reset_num_timesteps=not continued,
                tb_log_name="ppo",
            )
        except KeyboardInterrupt:
            interrupted = run_dir / "interrupted.zip"
            save_atomically(model, interrupted)
            # SubprocVecEnv.close() would first wait for the step results of every worker, some of
            # which Ctrl-C's step_wait already read: forever. The workers ignore SIGINT, so they
            # read the close command right after the result nobody collects.
            if hasattr(venv.unwrapped, "waiting"):
                venv.unwrapped.waiting = False
            raise TrainingInterrupted(interrupted, model.num_timesteps) from None
        final = run_dir / "final_model.zip"
        save_atomically(model, final)
        log.info("saved %s after %d steps", final, model.num_timesteps)
        return final
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
        venv.close()


#: ``--resume`` without a file: the run's newest checkpoint.
LATEST = "latest"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, required=True, help="training config (TOML)")
    parser.add_argument(
        "--resume",
        nargs="?",
        const=LATEST,
        metavar="CKPT.zip",
        help="continue the run: from its newest checkpoint (or interrupted.zip), or from CKPT.zip",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="delete the run directory's previous run and start afresh"
    )
    parser.add_argument(
        "overrides", nargs="*", metavar="KEY=VALUE", help="config overrides, e.g. ppo.n_steps=256"
    )


def resume_checkpoint(value: str | None, run_dir: Path) -> Path | None:
    """The checkpoint ``--resume`` names (None: a new run)."""
    if value is None:
        return None
    if value == LATEST:
        return latest_checkpoint(run_dir)
    path = Path(value)
    if not path.is_file():
        hint = "; put KEY=VALUE overrides before --resume" if "=" in value else ""
        raise UserError(f"--resume {value}: file not found{hint}")
    return path


def command(args: argparse.Namespace) -> int:
    config = load_train_config(args.config, args.overrides)
    if args.resume is not None and args.overwrite:
        raise UserError("--resume and --overwrite exclude each other")
    resume = resume_checkpoint(args.resume, config.run_dir)
    if config.ppo.init_from and resume is None:
        initial_model(Path(config.ppo.init_from))  # before the run directory: a typo leaves none
    with run_lock(config.run_dir):
        prepare_run_dir(config, resume is not None, args.overwrite)
        try:
            final = train(config, resume)
        except TrainingInterrupted as exc:
            print(f"avoid-train: {exc}", file=sys.stderr)
            return 130
    print(f"final model: {final}")
    return 0
