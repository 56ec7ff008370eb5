"""What a training run and an evaluation record: the recorders, Lightning callbacks that write a run's
files (their names and places: ``nerfexp.rundir``) and log its scores.

In a distributed run (``trainer=ddp``) each process evaluates its share of the images; the recorders
gather every image's scores and renders to all processes (``gather_evaluations``), and only global
rank 0 writes files and logs, so the numbers are those of one process scoring every image.
"""

import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import lightning as L
import torch

from nerfexp import manifest
from nerfexp.files import atomic_write
from nerfexp.kernels import prepare, prepared_line, seconds_spent
from nerfexp.machine_share import Sample, available_cpus, others_cpu_s, sample, share_record
from nerfexp.pixels import depth_image, png_bytes, to_uint8
from nerfexp.rundir.labels import NO_LABELS
from nerfexp.rundir.layout import (
    EVAL,
    METRICS,
    RESULTS,
    TEST_DIR,
    append_metrics,
    checkpoint_record,
    machine,
    read_metrics,
    write_json,
)
from nerfexp.scoring.collapse import blank_views
from nerfexp.scoring.measures import MEASURES, image_means, image_scores
from nerfexp.scoring.perceptual import CUSTOM, PUBLISHED
from nerfexp.training.budgets import (
    AUTO,
    COST_SHARE,
    DEFAULT_FRACTIONS,
    SMALL_COST_S,
    affordable_budgets,
    budget_entry,
    budget_fractions,
    budget_text,
    cost_text,
    costly_line,
    reduced_line,
    score_test_views,
    scoring_seconds,
    training_estimate_s,
)
from nerfexp.training.loggers import log_hyperparams, log_image, log_labels
from nerfexp.training.resume import RESUMES, SETTINGS

log = logging.getLogger("nerfexp")

IMAGES = ("rgb", "depth", "opacity", "target")  # what an evaluation step returns per image, besides its scores


def gather_evaluations(trainer: L.Trainer, outputs: dict) -> list[dict]:
    """The outputs of this evaluation step on every process (``NeRFModule._evaluate``: "index", the
    ``MEASURES`` and the images ``IMAGES``), one dict per process in rank order; on one process ``[outputs]``.

    Every process must call it at every step (it is a collective): Lightning's distributed sampler
    gives each process the same number of images, repeating some where they do not divide evenly,
    so callers keep the first result for each image index. Measures travel as float64, exactly (NaN too)."""
    if trainer.world_size == 1:
        return [outputs]
    images = outputs["rgb"]
    numbers = torch.tensor([outputs["index"], *(outputs.get(name, math.nan) for name in MEASURES)],
                           dtype=torch.float64, device=images.device)
    gathered = {key: trainer.strategy.all_gather(outputs[key]) for key in IMAGES}  # each [world size, ...]
    numbers = trainer.strategy.all_gather(numbers)  # [world size, 1 + len(MEASURES)]
    return [{"index": int(numbers[r, 0]), **{name: float(numbers[r, 1 + i]) for i, name in enumerate(MEASURES)},
             **{key: gathered[key][r] for key in IMAGES}} for r in range(trainer.world_size)]


def scores_record(scores: dict[int, dict[str, float]]) -> dict:
    """What ``results.json`` and ``eval.json`` say of the test views scored ``{index: {"psnr", "ssim", "lpips"}}``:
    the means ``test_psnr``, ``test_ssim`` and, in view order, ``test_views`` (the indices, which name the
    renders ``test/r_{i}.png``), ``test_psnr_per_view`` and ``test_ssim_per_view``; with LPIPS scored
    (``scored``), ``test_lpips`` and ``test_lpips_per_view`` too (absent otherwise, never NaN)."""
    views, means = sorted(scores), image_means(scores)
    return {**{f"test_{name}": means[name] for name in means}, "test_views": views,
            **{f"test_{name}_per_view": [scores[i][name] for i in views] for name in means}}


def lpips_text(scores: dict, prefix: str = "") -> str:
    """", LPIPS 0.1234" (4 decimals) where ``scores`` has ``{prefix}lpips``; ", LPIPS with your own weights (not
    comparable) 0.1234" where it has ``{prefix}lpips_custom`` instead; else ""."""
    if f"{prefix}{PUBLISHED}" in scores:
        return f", LPIPS {scores[f'{prefix}{PUBLISHED}']:.4f}"
    if f"{prefix}{CUSTOM}" in scores:
        return f", LPIPS with your own weights (not comparable) {scores[f'{prefix}{CUSTOM}']:.4f}"
    return ""


def collapse_record(scores: dict[int, dict[str, float]]) -> dict[str, str | None]:
    """What ``results.json`` and ``eval.json`` say of whether the test views ``{index: {..., "contrast"}}``
    rendered anything: ``collapse``, where every one rendered nothing (``nerfexp.scoring.collapse.blank_views``),
    the line that says so, which a report never ranks; else null."""
    contrasts = {index: measures["contrast"] for index, measures in scores.items()}
    return {"collapse": blank_views(contrasts, "test")}


def scores_text(results: dict) -> str:
    """A run's test scores in words, from ``results.json`` or ``eval.json``: the PSNR in dB (2 decimals), the
    SSIM (4), and the LPIPS (4) where it was scored (``lpips_text``); where the run ``collapse``d, the scores
    are said to be of a render of nothing, and how."""
    collapse = results.get("collapse")
    of_nothing = f", scores of a render of nothing: {collapse}" if collapse else ""
    return (f"test PSNR {results['test_psnr']:.2f} dB, SSIM {results['test_ssim']:.4f}{lpips_text(results, 'test_')}"
            f"{of_nothing}")


def keep_metrics_through(output_dir: Path, step: int) -> None:
    """Rewrite ``metrics.jsonl`` in ``output_dir`` without its lines of steps after ``step`` (and a last line
    cut short), where it has any; otherwise leave it untouched."""
    keep_metrics(output_dir, lambda record: record["step"] <= step)


def keep_metrics(output_dir: Path, keep: Callable[[dict], bool]) -> None:
    """Rewrite ``metrics.jsonl`` in ``output_dir`` with only the lines (read whole: a last line cut short is
    left out) that ``keep`` keeps, where that changes it; otherwise leave it untouched."""
    kept = [record for record in read_metrics(output_dir) if keep(record)]
    path = Path(output_dir) / METRICS
    text = "".join(json.dumps(record) + "\n" for record in kept).encode()
    if path.exists() and path.read_bytes() != text:
        atomic_write(path, text)
        manifest.record(output_dir, [METRICS])


class RunRecorder(L.Callback):
    """Writes a run's metrics, results and test renders; times the training in wall-clock seconds (and its CPU
    time, and how busy other processes kept the machine meanwhile: ``nerfexp.machine_share``);
    logs ``val/psnr``, ``val/ssim``, ``test/psnr``, ``test/ssim`` (means over the images), and
    ``val/lpips``, ``test/lpips`` where LPIPS is scored.

    The last step is always validated (``val_psnr`` of a run shorter than ``scale.val_every`` too), and
    each validation logs one line: step, PSNR, SSIM (and LPIPS) and the training's wall-clock seconds so far. Each
    test view's render, its ground truth and their absolute difference (per channel, in [0, 1]) are
    saved as ``test/r_{i}.png``, ``r_{i}_target.png``, ``r_{i}_error.png``, with ``r_{i}_depth.png``. Every
    file it writes is recorded in the run's manifest as it is written (``nerfexp.manifest``). Where every test
    view rendered nothing, ``results.json``'s ``collapse`` says so (``collapse_record``), whatever the guard did.
    Where the scene says where its files came from (a scene by name: ``Scene.source``, its archive's digest) or which
    frames it left out for their missing images (``Scene.frames_left_out``), ``results.json`` holds them as ``scene``
    and ``frames_left_out``; the test images' [width, height] as ``test_resolution``.

    The fused kernels the module's training runs (``NeRFModule.kernels``) are built, or read from the cache, as
    training starts and before its clock does (``nerfexp.kernels.prepare``), what each came to said in one line
    (built, loaded from the cache, not built and why, or off: never "ready" for one the run will not use); a
    kernel first asked for inside the clock is taken out of it all the same (``nerfexp.kernels.seconds_spent``).
    ``results.json`` records those seconds apart, ``kernel_build_s``, never in ``train_time_s``; beside them
    ``cpu_time_s``, ``other_load``, ``cpus`` (``nerfexp.machine_share.share_record``) and
    ``torch_threads``.

    The elapsed time (and CPU time, others' CPU time and kernel seconds) and the last validation PSNR are part of
    the checkpoint, so a resumed run keeps
    counting from where it stopped, and a test in processes that did not train (``trainer=ddp`` spawns
    new ones for ``trainer.test``) reports the step, time and validation of the checkpoint it tests. At
    the end of training the last checkpoint is written again, after the last validation: Lightning's
    ``ModelCheckpoint`` keeps the one of its last save, taken before that validation (or at an earlier
    step where ``scale.steps`` is not a multiple of ``scale.val_every``).

    Each checkpoint also records the run's ``settings`` (``nerfexp.training.resume.checkpoint_settings``)
    and ``resumes`` (``nerfexp.training.resume.resume_record``), which ``results.json`` lists too, so that
    a resume is checked against the settings that trained the checkpoint. The run's ``labels`` (its tags and
    notes, ``nerfexp.rundir.labels``) go to ``results.json`` and to each logger. A resumed run's
    ``metrics.jsonl`` keeps the lines of the steps up to its checkpoint's: later ones came from training
    that the resumed run does again, and would stand twice for the same steps.

    ``test_budgets`` (fractions of ``trainer.max_steps``, or ``auto``: ``nerfexp.training.budgets``): after each
    budget's step the clock stops, the test views are scored with the weights then, exactly as the final test scores
    them (``score_test_views``: no images written), and the clock goes on; each budget's scores go to
    ``metrics.jsonl`` (split test) and to each logger (``test/psnr``, ...) at its step, with one line in the log.
    A budget's cost is estimated before it is paid (the first budget's first view times the views, later the last
    budget's scoring, ``_affordable``): under ``auto`` the budgets that would take the scoring past ``COST_SHARE``
    of the training's estimated time are not scored, said in one line; a list the user gives is scored as set,
    with a line where it costs more. ``results.json``'s
    ``test_budgets`` lists them with the final test's last (``budget_entry``), and ``budget_scoring_s`` the
    seconds their scoring took, never in ``train_time_s``. The budgets scored are part of the checkpoint; a run
    resumed at a budget's step whose checkpoint does not hold it (saved before it was scored, or a finished run
    trained further) scores it before its first step.
    """

    def __init__(self, output_dir: str, choices: dict, run_config: dict | None = None,
                 overrides: list[str] = (), settings: dict | None = None, resumes: list[dict] = (),
                 labels: dict | None = None, bounds: str | None = None, test_budgets: list[float] | str = ()):
        self.output_dir = Path(output_dir)
        self.bounds = bounds  # where the scene's near and far came from (``Scene.bounds_rule``), or None
        self.choices, self.run_config, self.overrides = dict(choices), run_config, list(overrides)
        self.settings = settings
        self.resumes = list(resumes)
        self.labels = {**NO_LABELS, **(labels or {})}  # {"tags": [...], "notes": text or None}
        self.last_val_psnr: float | None = None
        self.elapsed_s, self._started, self.steps, self.trained = 0.0, None, 0, False
        self.cpu_s: float | None = 0.0  # the training's CPU seconds (None: a resumed checkpoint did not record them)
        self.others_s: float | None = 0.0  # other processes' busy CPU seconds meanwhile (None: not measured)
        self.kernel_build_s = 0.0  # seconds spent getting kernels, outside the clock
        self._start: Sample | None = None  # the clock's start (``nerfexp.machine_share.sample``)
        self._spent_at_start = self._spent_at_fit = 0.0  # ``nerfexp.kernels.seconds_spent`` then
        self.torch_threads = torch.get_num_threads()  # as training starts
        self.thread_changes: list[dict] = []  # nerfexp.training.callbacks.ThreadsFollowLoad's, in step order
        self._scores: dict[int, dict[str, float]] = {}  # image index -> its measures (MEASURES)
        self.auto = test_budgets == AUTO  # DEFAULT_FRACTIONS, as many as their cost allows (_affordable)
        self.test_budgets = [float(f) for f in (DEFAULT_FRACTIONS if self.auto else test_budgets)]  # of max_steps
        self.dropped: set[int] = set()  # the budgets' steps auto does not score: their cost (_affordable)
        self._cost_said = False  # whether a user's list of budgets has said what it costs (_affordable)
        self.budgets: list[dict] = []  # the budgets scored so far (budget_entry), in step order
        self._test_started: float | None = None  # the final test's start (time.perf_counter)

    def wall_time_s(self) -> float:
        """The training's wall-clock seconds so far, those spent getting kernels inside the clock taken out."""
        if self._started is None:
            return self.elapsed_s
        return self.elapsed_s + time.perf_counter() - self._started - (seconds_spent() - self._spent_at_start)

    def totals(self) -> tuple[float, float | None, float | None]:
        """The training's wall seconds (``wall_time_s``), CPU seconds and other processes' busy CPU seconds so far
        (``nerfexp.machine_share.others_cpu_s``; None where not measured)."""
        if self._start is None:
            return self.elapsed_s, self.cpu_s, self.others_s
        now = sample()
        others = others_cpu_s(self._start, now)
        return (self.wall_time_s(), None if self.cpu_s is None else self.cpu_s + now.cpu_s - self._start.cpu_s,
                None if self.others_s is None or others is None else self.others_s + others)

    def on_fit_start(self, trainer, pl_module):
        """Declare the run's hyper-parameters (its choices, overrides and the labels it has) to each logger
        (``nerfexp.training.loggers``: TensorBoard's HPARAMS view, MLflow's parameters, ...), and its labels
        where a logger keeps them apart (W&B's tags and notes, MLflow's run tags)."""
        self._spent_at_fit = seconds_spent()
        if trainer.is_global_zero:
            params = {**self.choices, **dict(o.lstrip("+~").split("=", 1) for o in self.overrides if "=" in o),
                      **{key: value for key, value in self.labels.items() if value}}
            for logger in trainer.loggers:
                log_hyperparams(logger, params)
                log_labels(logger, **self.labels)

    def on_train_start(self, trainer, pl_module):
        """The kernels the training runs, built or read now, then the clock started."""
        names = pl_module.kernels()
        if names:
            outcomes = prepare(names)  # built, loaded, not built (why) or off: what each came to
            if trainer.is_global_zero:
                log.info("%s", prepared_line(outcomes))
        self.torch_threads = torch.get_num_threads()
        self._start_clock()

    def _start_clock(self) -> None:
        """The training clock started (or started again after a pause, ``_stop_clock``)."""
        self._spent_at_start = seconds_spent()
        self._start = sample()
        self._started = self._start.wall_s

    def _stop_clock(self) -> None:
        """The training clock stopped: its wall, CPU and other processes' CPU seconds so far (``totals``) kept, and
        nothing counted until ``_start_clock``."""
        self.elapsed_s, self.cpu_s, self.others_s = self.totals()
        self._started, self._start = None, None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        """A run resumed at a budget's step whose checkpoint does not hold it scores it before its next step; the
        test line of that step in ``metrics.jsonl`` (a scoring of the same weights that the checkpoint does not
        hold: a finished run's final test, a budget scored after the checkpoint was saved) is replaced."""
        if self._unscored_budget(trainer):
            if trainer.is_global_zero:
                step = trainer.global_step
                keep_metrics(self.output_dir, lambda record: (record["step"], record["split"]) != (step, "test"))
            self._score_budget(trainer, pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps = trainer.global_step  # the step of the weights that the evaluations score
        if trainer.max_steps > 0 and self.steps >= trainer.max_steps:
            # Lightning validates every val_check_interval steps, and also after the step that asks the
            # loop to stop: so the last weights are validated whatever scale.val_every is (once, where
            # it is also a multiple of val_every)
            trainer.should_stop = True
        elif not trainer.should_stop and self._unscored_budget(trainer):  # (stopping here: the end's test scores it)
            self._score_budget(trainer, pl_module)

    def _unscored_budget(self, trainer) -> bool:
        """Whether the weights now are those of a budget's step (``budget_fractions``) not scored yet."""
        step = trainer.global_step
        return (step in budget_fractions(self.test_budgets, trainer.max_steps) and step not in self.dropped
                and all(entry["step"] != step for entry in self.budgets))

    def _evaluations(self, trainer, pl_module, step: int) -> float | None:
        """The network evaluations of training's first ``step`` steps: evaluations per ray x the rays of a step (all
        processes') x ``step``; None where the data module does not say its batch's rays."""
        batch_rays = getattr(trainer.datamodule, "batch_rays", None)
        return float(pl_module.renderer.evaluations_per_ray * batch_rays * step) if batch_rays else None

    def _score_budget(self, trainer, pl_module) -> None:
        """The test views scored now (``score_test_views``), outside the training clock: the budget recorded
        (``budget_entry``) by every process (each scored every view), and by rank 0 appended to ``metrics.jsonl``,
        logged to each logger at its step and said in one line."""
        step = trainer.global_step
        self._stop_clock()
        started = time.perf_counter()
        if self.budgets:  # the last budget's scoring: what the next costs, before any of it is paid
            last = self.budgets[-1]["score_s"]
            scored = self._affordable(trainer, last, cost_text(last, None, 0))
            scores = score_test_views(trainer, pl_module) if scored else {}
        else:  # the first view's seconds times the views, asked after the first view
            scores = score_test_views(trainer, pl_module, lambda views, seconds, total: views > 1 or self._affordable(
                trainer, seconds * total, cost_text(seconds * total, seconds, total), paid=views == total))
        if step in self.dropped:  # its cost is more than auto's budgets may take: the clock goes on
            self._start_clock()
            return
        score_s = time.perf_counter() - started
        entry = budget_entry(step, self.elapsed_s, self._evaluations(trainer, pl_module, step), scores, score_s)
        self.budgets.append(entry)
        if trainer.is_global_zero:
            self._record_means(trainer, "test", image_means(scores), step, self.elapsed_s)
            fraction = budget_fractions(self.test_budgets, trainer.max_steps)[step]
            log.info("step %d/%d: %s at a budget of %s (%.2f s of scoring, outside the training clock)", step,
                     trainer.max_steps, scores_text(entry), budget_text(fraction), score_s)
        self._start_clock()

    def _affordable(self, trainer, cost_each_s: float, cost: str, paid: bool = False) -> bool:
        """Whether the budget of this step is scored, each budget from it on estimated to cost ``cost_each_s``
        seconds (``cost``: how, in words). Under ``auto`` those of them that would take the scoring past
        ``COST_SHARE`` of the training's estimated time (``affordable_budgets``; the latest first) are ``dropped``,
        said in one line (``reduced_line``; rank 0's choice on every process), this step's unless it is ``paid``
        (its every view scored already). A user's list is kept whole, with a line where it costs more
        (``costly_line``)."""
        step, max_steps = trainer.global_step, trainer.max_steps
        fractions = budget_fractions(self.test_budgets, max_steps)
        scored = {entry["step"] for entry in self.budgets}
        pending = [s for s in fractions if s >= step and s not in self.dropped and s not in scored]
        training_s = training_estimate_s(self.elapsed_s, step, max_steps)
        spent_s = math.fsum(entry["score_s"] for entry in self.budgets)
        if not self.auto:
            total_s = len(pending) * cost_each_s
            if not self._cost_said and spent_s + total_s > max(COST_SHARE * training_s, SMALL_COST_S):
                self._cost_said = True
                if trainer.is_global_zero:
                    log.info("%s", costly_line(self.test_budgets, cost, total_s, training_s))
            return True
        kept = affordable_budgets(len(pending), cost_each_s, spent_s, training_s)
        kept = trainer.strategy.broadcast(max(kept, 1) if paid else kept, src=0)
        if kept < len(pending):
            self.dropped.update(pending[kept:])
            if trainer.is_global_zero:
                kept_fractions = [fractions[s] for s in sorted(scored | set(pending[:kept])) if s in fractions]
                log.info("%s", reduced_line(kept_fractions, [fractions[s] for s in pending[kept:]], cost, training_s))
        return kept > 0

    def on_train_end(self, trainer, pl_module):
        wall, cpu, others = self.totals()
        if trainer.world_size > 1 and cpu is not None:  # the run's CPU time is all its processes'
            own = cpu
            cpu = float(trainer.strategy.reduce(torch.tensor(cpu, dtype=torch.float64, device=pl_module.device),
                                                reduce_op="sum"))
            if others is not None and trainer.num_nodes == 1:  # this machine's counters hold the others' too
                others = max(0.0, others - (cpu - own))
        self.kernel_build_s += seconds_spent() - self._spent_at_fit
        self.elapsed_s, self.cpu_s, self.others_s = wall, cpu, others
        self._started, self._start, self.steps = None, None, trainer.global_step
        self.trained = True
        checkpoint = trainer.checkpoint_callback
        if checkpoint is not None and checkpoint.last_model_path:  # none yet: ModelCheckpoint saves it next
            trainer.save_checkpoint(checkpoint.last_model_path)

    def state_dict(self) -> dict:
        wall, cpu, others = self.totals()
        kernels = self.kernel_build_s + (seconds_spent() - self._spent_at_fit if not self.trained else 0.0)
        return {"elapsed_s": wall, "last_val_psnr": self.last_val_psnr, "cpu_time_s": cpu, "others_cpu_s": others,
                "kernel_build_s": kernels, "torch_threads": self.torch_threads,
                "thread_changes": [dict(change) for change in self.thread_changes],
                "test_budgets": [dict(entry) for entry in self.budgets]}

    def load_state_dict(self, state_dict: dict) -> None:
        """What a checkpoint recorded of the training so far; of an earlier nerfexp's, which recorded no CPU
        times, those are unknown (None) and stay so, and no budget was scored."""
        if not self.trained:  # a test after training in this process keeps what it measured
            self.elapsed_s, self.last_val_psnr = state_dict["elapsed_s"], state_dict.get("last_val_psnr")
            self.cpu_s, self.others_s = state_dict.get("cpu_time_s"), state_dict.get("others_cpu_s")
            self.kernel_build_s = state_dict.get("kernel_build_s", 0.0)
            self.torch_threads = state_dict.get("torch_threads", self.torch_threads)
            self.thread_changes[:] = [dict(change) for change in state_dict.get("thread_changes", [])]
            self.budgets = [dict(entry) for entry in state_dict.get("test_budgets", [])]

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        if self.settings is not None:
            checkpoint[SETTINGS] = self.settings
        checkpoint[RESUMES] = self.resumes

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        if not self.trained:
            self.steps = checkpoint["global_step"]
            if trainer.is_global_zero:
                keep_metrics_through(self.output_dir, self.steps)

    def _collect(self, trainer, pl_module, outputs: dict, split: str) -> None:
        for item in gather_evaluations(trainer, outputs):
            index = item["index"]
            if index in self._scores:  # a repeat of the distributed sampler's padding
                continue
            self._scores[index] = image_scores(item, split, self.steps)
            if trainer.is_global_zero:
                self._write_images(trainer, pl_module, item, split)

    def _write_images(self, trainer, pl_module, item: dict, split: str) -> None:
        index, renderer = item["index"], pl_module.renderer
        depth = depth_image(item["depth"], item["opacity"], renderer.near, renderer.ray_far)
        if split == "test":
            images = {"": item["rgb"], "_target": item["target"], "_depth": depth,
                      "_error": (item["rgb"] - item["target"]).abs()}
            names = [f"{TEST_DIR}/r_{index}{suffix}.png" for suffix in images]
            for name, image in zip(names, images.values(), strict=True):
                atomic_write(self.output_dir / name, png_bytes(to_uint8(image)))
            manifest.record(self.output_dir, names)
        if index < 4 and trainer.loggers and not trainer.sanity_checking:
            side_by_side = torch.cat([item["rgb"], item["target"], depth[..., None].expand(-1, -1, 3)], 1)
            for logger in trainer.loggers:
                log_image(logger, f"{split}/render_target_depth/{index}", to_uint8(side_by_side), self.steps,
                          self.output_dir)

    def _flush(self, trainer, split: str) -> dict[int, dict[str, float]]:
        """The scores of the images scored since the last flush; rank 0 appends their means to
        ``metrics.jsonl`` and logs them at the step of the weights scored. A validation's mean PSNR
        becomes ``last_val_psnr``."""
        scores, self._scores = self._scores, {}
        means = image_means(scores)
        if split == "val":
            self.last_val_psnr = means["psnr"]
        if trainer.is_global_zero:
            wall_time_s = self.wall_time_s()
            self._record_means(trainer, split, means, self.steps, wall_time_s)
            if split == "val":
                log.info("step %d/%d: validation PSNR %.2f dB, SSIM %.4f%s after %.0f s of training", self.steps,
                         trainer.max_steps, means["psnr"], means["ssim"], lpips_text(means), wall_time_s)
        return scores

    def _record_means(self, trainer, split: str, means: dict[str, float], step: int, wall_time_s: float) -> None:
        """The means over the images of ``split`` scored at ``step`` appended to ``metrics.jsonl``, with the
        training's seconds then, and logged to each logger as ``{split}/{name}`` at ``step``."""
        append_metrics(self.output_dir, {"step": step, "wall_time_s": wall_time_s, "split": split, **means})
        for logger in trainer.loggers:
            logger.log_metrics({f"{split}/{name}": value for name, value in means.items()}, step)

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        if not trainer.sanity_checking:
            self._collect(trainer, pl_module, outputs, "val")

    def on_validation_epoch_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self._flush(trainer, "val")

    def on_test_start(self, trainer, pl_module):
        self._test_started = time.perf_counter()

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        self._collect(trainer, pl_module, outputs, "test")

    def on_test_epoch_end(self, trainer, pl_module):
        """``results.json``; its ``test_budgets`` end with this test's scores, at the step it scores (the step the
        run stopped at), and keep the budgets scored before that step."""
        test_s = time.perf_counter() - self._test_started if self._test_started is not None else 0.0
        scores, steps = self._flush(trainer, "test"), self.steps
        if not trainer.is_global_zero:
            return
        renderer, batch_rays = pl_module.renderer, getattr(trainer.datamodule, "batch_rays", None)
        test_scores = scores_record(scores)
        end = budget_entry(steps, self.elapsed_s, self._evaluations(trainer, pl_module, steps), scores, test_s)
        budgets = [*(entry for entry in self.budgets if entry["step"] < steps), end]
        results = {
            **test_scores, **pl_module.lpips_record(test_scores), **collapse_record(scores),
            "val_psnr": self.last_val_psnr,
            "train_time_s": self.elapsed_s, "steps": steps, "kernel_build_s": self.kernel_build_s,
            **share_record(self.elapsed_s, self.cpu_s, self.others_s, available_cpus()),
            "torch_threads": self.torch_threads, "thread_changes": self.thread_changes,
            "time_per_step_s": self.elapsed_s / max(steps, 1),
            "rays_per_s": batch_rays * steps / self.elapsed_s if batch_rays and self.elapsed_s > 0 else None,
            "batch_rays": batch_rays, "processes": trainer.world_size, "precision": str(trainer.precision),
            "n_params": sum(p.numel() for p in pl_module.parameters()), "test_protocol": pl_module.test_protocol,
            "test_cameras": pl_module.test_cameras, "evaluations_per_ray": renderer.evaluations_per_ray,
            "colour_evaluations_per_ray": renderer.colour_evaluations_per_ray,
            "machine": machine(), "choices": self.choices, "overrides": self.overrides, **self.labels,
            "config": self.run_config, "resumes": self.resumes,
            "test_budgets": budgets, "budget_scoring_s": scoring_seconds(budgets),
        }
        scene = trainer.datamodule.scene if trainer.datamodule is not None else None
        rule = scene.split_rule() if scene is not None else None
        if rule is not None:  # how the views were split, where a rule made the split
            results["split"] = rule
        if scene is not None:  # a scene by name: its archive's digest; the frames left out for their missing images
            for key, record in (("scene", scene.source()), ("frames_left_out", scene.frames_left_out())):
                if record is not None:
                    results[key] = record
        if self.bounds is not None:  # where near and far came from, where the scene found them
            results["bounds"] = self.bounds
        if trainer.datamodule is not None:  # the test images' [width, height]: a published score's protocol has it
            test = trainer.datamodule.scored_views("test")["test"]
            results["test_resolution"] = [test.width, test.height]
        if trainer.datamodule is not None and trainer.datamodule.split_check is not None:  # no view seen in training
            results["split_check"] = trainer.datamodule.split_check
        if trainer.ckpt_path is not None:  # the weights scored: the checkpoint the test loaded
            results["checkpoint"] = checkpoint_record(self.output_dir, Path(trainer.ckpt_path))
        write_json(self.output_dir / RESULTS, results)


class EvalRecorder(L.Callback):
    """Scores a checkpoint on the test split: ``eval.json`` in ``output_dir`` holds the test scores as
    ``results.json`` does (``scores_record``: means and per view; the LPIPS weights' SHA-256,
    ``NeRFModule.lpips_record``; ``collapse_record``), the ``checkpoint``, its ``step`` and the ``machine``."""

    def __init__(self, output_dir: str | Path, checkpoint: str | Path, step: int):
        self.output_dir, self.checkpoint, self.step = Path(output_dir), Path(checkpoint), step
        self._scores: dict[int, dict[str, float]] = {}  # image index -> its measures (MEASURES)

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        for item in gather_evaluations(trainer, outputs):
            self._scores.setdefault(item["index"], image_scores(item, "test", self.step))

    def on_test_epoch_end(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        test_scores = scores_record(self._scores)
        results = {**test_scores, **pl_module.lpips_record(test_scores), **collapse_record(self._scores),
                   "test_protocol": pl_module.test_protocol, "test_cameras": pl_module.test_cameras,
                   "checkpoint": str(self.checkpoint.resolve()), "step": self.step,
                   "processes": trainer.world_size, "machine": machine()}
        write_json(self.output_dir / EVAL, results)
