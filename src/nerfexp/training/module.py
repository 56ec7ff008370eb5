"""The LightningModule: trains a ``VolumeRenderer`` on ray batches and scores whole images."""

import contextlib
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterator

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.errors import ConfigError
from nerfexp.nerf.appearance import FULL_IMAGE, CodeFit
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.encodings import Encoding
from nerfexp.nerf.poses import PoseCorrection, PoseFit
from nerfexp.nerf.schedules import warmup_exponential_decay
from nerfexp.nerf.volume_renderer import VolumeRenderer, final_output
from nerfexp.rundir.trained import current_weights
from nerfexp.scoring.collapse import contrast
from nerfexp.scoring.metrics import psnr, ssim
from nerfexp.scoring.perceptual import LPIPS_NAMES, NOT_SCORED, ImageTooSmall, LpipsScorer, lpips_scorer
from nerfexp.scoring.scorer import TestScorer, check_scored
from nerfexp.training.optimizers import update_kernels

log = logging.getLogger(__name__)


class NeRFModule(L.LightningModule):
    """Loss = sum over networks of the MSE of their colours (coarse + fine), plus the regularizers the
    renderer's outputs hold (``regularizer_sums``: the proposal networks' losses, Ref-NeRF's normal
    penalties), each logged as ``train/<name>``; Adam whose learning
    rate decays exponentially from the optimizer's ``lr`` to ``lr_final`` over ``trainer.max_steps``,
    ramped up linearly over the first ``lr_warmup_steps`` (0: none, as in the paper).

    Evaluation renders whole images in chunks of ``chunk`` rays (memory bounded at any resolution)
    and scores the fine network's image (the only one without hierarchy): PSNR, SSIM and LPIPS
    (``nerfexp.scoring.perceptual``). ``lpips``: auto scores LPIPS where AlexNet's weights are found
    (``lpips_weights``, else the torch hub cache) and images are large enough, and says once why not where
    they are not; true requires it (a ConfigError otherwise); false leaves it out. Only torchvision's published
    weights score ``lpips``; ``lpips_custom``: the file ``lpips_weights`` names is the user's own on purpose,
    scored as ``lpips_custom`` (``lpips_record`` gives the weights' SHA-256 for the records). Its network is built
    once, at ``setup``, by the commands that evaluate (not by those that only render).

    ``diagnostics`` holds what the latest training batch showed of each network, detached (no graph,
    no copy): ``{"coarse": {"loss": [], "opacity": [B]}, "fine": {...}}`` (only "coarse" without
    hierarchy), the colour loss and the rendered opacity of each of the B rays. Callbacks read it
    between the backward pass and the optimizer step (``nerfexp.training.guards.TrainingGuard``), which
    ``training_step``'s return value does not reach, and at no cost of extra rendering.

    With an occupancy grid (``renderer.grid``) the module updates it after each training step's
    rendering, from the same seeded random stream (so a step stays a function of the batch and the
    state). The grid and the hash grid encoding work inside the scene's box (``nerfexp.nerf.bounds``):
    the module gives it to them when training starts if they have none (the datamodule's ``scene_box``,
    ``nerfexp.data.datamodule.RayDataModule``).
    Each step logs ``train/samples_per_ray`` (evaluated by the networks, all of them together) and
    ``train/rays_per_s`` (rays over the step's host wall-clock time).
    ``compile``: each network is compiled with ``torch.compile`` (in place, so checkpoints keep their keys).
    Encodings with sparse gradients (``Encoding.sparse_gradients``: the hash tables', with
    ``HashGridEncoding(sparse_gradients=True)``) get dense ones when more than one process trains (``on_fit_start``).
    """

    def __init__(self, renderer: VolumeRenderer, optimizer: Callable[..., torch.optim.Optimizer],
                 lr_final: float, chunk: int = 8192, lr_warmup_steps: int = 0, compile: bool = False,
                 lpips: bool | str = "auto", lpips_weights: str | None = None, lpips_custom: bool = False,
                 camera_opt: Callable[[int], PoseCorrection] | None = None,
                 appearance_fit: CodeFit | None = None, test_protocol: str = FULL_IMAGE,
                 test_camera_fit: PoseFit | None = None):
        super().__init__()
        self.test_camera_fit = test_camera_fit  # each test camera refined, the networks frozen, or None (given)
        self.appearance_fit = appearance_fit  # NeRF-W's fit of a test image's code (appearance=embedding), or None
        self.test_protocol = test_protocol  # the protocol of the headline test scores (TestScorer.protocol_scores)
        self.pose_correction_of = camera_opt  # n_views -> PoseCorrection, or None (camera_opt=off)
        self.camera_opt: PoseCorrection | None = None  # built with the training views' number (build_camera_opt)
        self.renderer, self.optimizer, self.lr_final, self.chunk = renderer, optimizer, lr_final, chunk
        self.lr_warmup_steps = lr_warmup_steps
        self.lpips, self.lpips_weights = lpips, lpips_weights
        self.lpips_custom = lpips_custom
        self.lpips_scorer: LpipsScorer | None = None  # built by setup
        self._lpips_decided = False
        self.diagnostics: dict[str, dict[str, Tensor]] = {}
        self._step_started: float | None = None
        self._batch_number = 0  # the training batch under way, counted from 1 (on_train_batch_start)
        if compile:
            check_compiler()
            for net in self.networks.values():
                net.compile(dynamic=True)  # packed batches change size every step

    @property
    def networks(self) -> dict[str, nn.Module]:
        """The renderer's networks under the names its outputs use (its sampler's ``field_names``): coarse and
        fine, or coarse alone."""
        return {name: getattr(self.renderer, name) for name in self.renderer.sampler.field_names}

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """One step on ``batch``; its stratified jitter is drawn from ``batch["seed"]`` where the batch
        has one (``RandomRays``), so that the step is a function of the batch and the weights alone."""
        batch = self.step_batch(batch)
        with seeded_random(batch.get("seed"), self.device):
            outputs = self.renderer(batch["origins"], batch["directions"], deterministic=False,
                                    viewdirs=batch.get("viewdirs"), codes=self.training_codes(batch))
            if self.renderer.grid is not None:  # after rendering: the jitter above is that of a run without grid
                self.renderer.grid.update(self.global_step, self.renderer.density_fns())
        losses = {name: F.mse_loss(out["rgb"], batch["rgb"]) for name, out in outputs.items()}
        self.diagnostics = {name: {"loss": losses[name].detach(), "opacity": out["opacity"].detach()}
                            for name, out in outputs.items()}
        regularizers = regularizer_sums(outputs)
        loss = sum(losses.values()) + sum(regularizers.values())
        if self.writes_logs:
            final = final_output(losses)
            self.log("train/loss", loss, prog_bar=True)
            self.log("train/psnr", -10 * torch.log10(final.detach()), prog_bar=True)
            self.log("train/lr", self.optimizers().param_groups[0]["lr"])
            for key, value in regularizers.items():
                self.log(f"train/{key}", value.detach())
            for key, value in self.renderer.stats.items():
                self.log(f"train/{key}", value)
        return loss

    @property
    def writes_logs(self) -> bool:
        """Whether the loggers write this training step's values: every ``trainer.log_every_n_steps`` steps.
        A value logged on another step is never written (a progress bar shows the last one written), and each
        ``self.log`` call costs a share of a small CPU step (docs/acceleration.md). Lightning writes them
        after the batches whose number is a multiple of it, and once it is to stop (each batch takes one
        optimizer step, so that number is ``global_step + 1`` as the batch starts)."""
        every = self.trainer.log_every_n_steps
        return every > 0 and (self._batch_number % every == 0 or self.trainer.should_stop)

    def check_scored_views(self, stage: str) -> None:
        """Every view that ``stage`` ("fit", "test") scores has pixels to score under the test protocol
        (``check_scored``, on the data module's ``scored_views``), where the trainer has a data module: a split
        with nothing to score stops the run before its first step or image, never scored NaN."""
        datamodule = self.trainer.datamodule
        if datamodule is not None:
            for split, views in datamodule.scored_views(stage).items():
                check_scored(views, split, self.test_protocol)

    def on_test_start(self) -> None:
        self.check_scored_views("test")

    def on_fit_start(self) -> None:
        """The views scored checked first (``check_scored_views``). With several processes (DDP), the encodings'
        gradients (the hash tables') are made dense: DDP all-reduces the gradients it expects dense (sparse ones
        only of nn.Embedding) and stops at a sparse one, and NCCL has no sparse all-reduce. LazyAdam then updates
        the tables as torch.optim.Adam does."""
        self.check_scored_views("fit")
        sparse = [m for m in self.renderer.modules() if isinstance(m, Encoding) and m.sparse_gradients]
        if self.trainer.world_size > 1 and sparse:
            for module in sparse:
                module.sparse_gradients = False
            if self.global_rank == 0:
                log.warning("%d processes: the hash tables' gradients are dense (DDP all-reduces dense gradients); "
                         "encoding.position.sparse_gradients=true applies to one process", self.trainer.world_size)

    def kernels(self) -> list[str]:
        """The fused kernels (``nerfexp.kernels``) this module's training runs where its parameters now are, each
        once: its encodings' own (``Encoding.kernels``), its sampler's (``Sampler.kernels``), and the sparse update of the parameters of those whose
        gradients are sparse (``nerfexp.training.optimizers.update_kernels``); ``RunRecorder`` builds them before
        its training clock starts."""
        encodings = [m for m in self.renderer.modules() if isinstance(m, Encoding)]
        sparse = [p for encoding in encodings if encoding.sparse_gradients for p in encoding.parameters()]
        return list(dict.fromkeys([*(name for encoding in encodings for name in encoding.kernels()),
                                   *self.renderer.sampler.kernels(), *update_kernels(sparse)]))

    def setup(self, stage: str) -> None:
        """Build the LPIPS scorer (``nerfexp.scoring.perceptual.lpips_scorer``), once per process: before
        training or a test, so that missing weights under ``lpips=true`` stop the run before any work."""
        self.size_appearance()
        if self._lpips_decided:
            return
        self.lpips_scorer, missing = lpips_scorer(self.lpips, self.lpips_weights, self.lpips_custom)
        self._lpips_decided = True
        if missing and self.global_rank == 0:
            log.info("%s", missing)

    def on_train_start(self) -> None:
        """The scene's extent, given to the components that work inside it where the config gave none: a
        contraction's inner region (around the training cameras), then the box of the occupancy grid and the hash
        grid (the contraction's box where there is one, else the scene's)."""
        contraction = self.renderer.contraction
        if contraction is not None and not contraction.has_inner:
            centre, radius = camera_ball(self.trainer.datamodule.camera_centres())
            contraction.set_inner(centre, radius)
            log.info("contraction: inner region of radius %.4g around %s", radius,
                     [round(v, 4) for v in centre.tolist()])
        unbounded = [m for m in self.renderer.modules() if isinstance(m, Bounded) and not m.has_bounds]
        if unbounded:
            box = (contraction.box if contraction is not None
                   else self.trainer.datamodule.scene_box(self.renderer.near, self.renderer.far))
            for module in unbounded:
                module.set_bounds(box.to(module.aabb.device))
            names = sorted({type(m).__name__ for m in unbounded})
            log.info("%s over %s", " and ".join(names), [[round(v, 3) for v in row] for row in box.tolist()])

    def on_train_batch_start(self, batch: dict, batch_idx: int) -> None:
        self._step_started = time.perf_counter()
        self._batch_number = self.trainer.global_step + 1

    def on_train_batch_end(self, outputs, batch: dict, batch_idx: int) -> None:
        if self._step_started is not None and self.writes_logs:
            self.log("train/rays_per_s", len(batch["origins"]) / (time.perf_counter() - self._step_started))

    @torch.no_grad()
    def render_image(self, origins: Tensor, directions: Tensor, viewdirs: Tensor | None = None,
                     code: Tensor | None = None) -> dict[str, Tensor]:
        """Deterministic render of rays [H, W, 3] (``viewdirs`` [H, W, 3] optional, see ``VolumeRenderer``)
        in chunks: ``rgb`` [H, W, 3], ``depth``, ``opacity`` [H, W]. ``code`` [D]: the image's appearance code
        (None: the renderer's test code, where it has an appearance embedding)."""
        H, W, _ = origins.shape
        flat_o, flat_d = origins.reshape(-1, 3), directions.reshape(-1, 3)
        flat_v = None if viewdirs is None else viewdirs.reshape(-1, 3)
        parts = []
        for start in range(0, H * W, self.chunk):
            chunk = slice(start, start + self.chunk)
            outputs = self.renderer(flat_o[chunk], flat_d[chunk], deterministic=True,
                                    viewdirs=None if flat_v is None else flat_v[chunk],
                                    codes=None if code is None else code.expand(len(flat_o[chunk]), -1))
            final = final_output(outputs)
            parts.append({key: final[key] for key in ("rgb", "depth", "opacity")})
        return {key: torch.cat([p[key] for p in parts]).reshape(H, W, *parts[0][key].shape[1:])
                for key in parts[0]}

    def _evaluate(self, batch: dict) -> dict:
        """One whole image scored (over the pixels its "mask" keeps, where it has one:
        ``nerfexp.scoring.metrics``; LPIPS with the render's masked pixels the target's): its "index",
        "psnr", "ssim", "lpips" and "lpips_custom" (``_lpips``), the render ("rgb", "depth", "opacity"), the
        "target", and the render's "contrast" against the target's (``nerfexp.scoring.collapse``: whether
        the view rendered anything, which the guard and the recorders judge). The means over images are
        logged by ``nerfexp.training.recorders.RunRecorder``, which gathers the images of all processes in a
        distributed run (a mean per process would weigh them wrongly)."""
        image = self.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))
        mask = batch.get("mask")  # [H, W]: the pixels that count, where the views have masks
        # LPIPS has no mask: the masked pixels of the render are the target's, so they differ nowhere
        scored = image["rgb"] if mask is None else torch.where(mask[..., None], image["rgb"], batch["rgb"])
        scores = {"psnr": psnr(image["rgb"], batch["rgb"], mask), "ssim": ssim(image["rgb"], batch["rgb"], mask),
                  **self._lpips(scored, batch["rgb"])}
        return {"index": int(batch["index"]), "target": batch["rgb"], **image, **scores,
                "contrast": contrast(image["rgb"], batch["rgb"], mask)}

    def _lpips(self, image: Tensor, target: Tensor) -> dict[str, float]:
        """LPIPS of ``image`` against ``target`` ([H, W, 3] each) under its scorer's name (``LpipsScorer.metric``:
        "lpips" with the published weights, "lpips_custom" with others), NaN under the other name; NaN under both
        where it is not scored: no scorer, or (under ``lpips=auto``) images smaller than AlexNet takes, which is said
        once and ends the scoring."""
        scores = dict.fromkeys(LPIPS_NAMES, NOT_SCORED)
        if self.lpips_scorer is None:
            return scores
        try:
            return {**scores, self.lpips_scorer.metric: self.lpips_scorer(image, target)}
        except ImageTooSmall as error:
            if self.lpips is True:
                raise ImageTooSmall(f"model.lpips=true: {error}") from None
            if self.global_rank == 0:
                log.info("LPIPS not scored: %s", error)
            self.lpips_scorer = None
            return scores

    def lpips_record(self, scores: dict) -> dict:
        """What ``results.json`` and ``eval.json`` say of the weights that scored the LPIPS in their ``scores``
        (``nerfexp.training.recorders.scores_record``): ``lpips_weights_sha256``, the SHA-256 of the AlexNet
        weights file, where ``test_lpips`` or ``test_lpips_custom`` is there; else nothing."""
        if self.lpips_scorer is None or not any(f"test_{name}" in scores for name in LPIPS_NAMES):
            return {}
        return {"lpips_weights_sha256": self.lpips_scorer.weights_sha256}

    def validation_step(self, batch: dict, batch_idx: int) -> dict:
        return self._evaluate(batch)

    def test_step(self, batch: dict, batch_idx: int) -> dict:
        scorer = self.test_scorer()
        batch, camera_fit = scorer.refined_camera(batch)
        return {**scorer.protocol_scores(self._evaluate(batch), batch), **camera_fit}

    def test_scorer(self) -> TestScorer:
        """How this module scores a test image (``nerfexp.scoring.scorer``): its renderer, protocol and test-time
        fits, its whole-image render and LPIPS, and its trainer's bars."""
        return TestScorer(renderer=self.renderer, protocol=self.test_protocol, appearance_fit=self.appearance_fit,
                          camera_fit=self.test_camera_fit, render_image=self.render_image, lpips=self._lpips,
                          draws_bars=self._draws_bars(), device=self.device)

    def _draws_bars(self) -> bool:
        """Whether the trainer running the test draws progress bars (its bar callback is on: standard output a
        terminal and ``trainer.enable_progress_bar``); False for a module called without a trainer."""
        try:
            bar = self.trainer.progress_bar_callback
        except RuntimeError:  # Lightning's "not attached to a Trainer": called directly
            return False
        return bar is not None and not bar.is_disabled

    @property
    def test_cameras(self) -> str:
        """How the test images were seen (``results.json``'s ``test_cameras``): from the cameras as the data gives
        them ("given"), or from each camera refined on the image's fitting pixels first ("refined")."""
        return "given" if self.test_camera_fit is None else "refined"

    # Per-image appearance (appearance=embedding, nerfexp.nerf.appearance): the codes, and the test protocols

    def training_codes(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The appearance codes [B, D] of a training batch's rays, by their "view" [B]; None without codes."""
        appearance = self.renderer.appearance
        return None if appearance is None else appearance(batch["view"])

    def size_appearance(self) -> None:
        """One appearance code per training view of the data module's (``AppearanceEmbedding.set_views``), where
        the codes have no rows yet (a checkpoint read back has its own); before the optimizer or a checkpoint's
        restore (Lightning calls ``setup`` before both)."""
        appearance = self.renderer.appearance
        if appearance is not None and appearance.n_views == 0:
            appearance.set_views(len(self.trainer.datamodule.train_views()))

    def parameter_groups(self) -> list[dict]:
        """The optimizer's parameter groups, ``named_parameter_groups`` in order."""
        return list(self.named_parameter_groups().values())

    def named_parameter_groups(self) -> dict[str, dict]:
        """{name: {"params": [...], option: value}}: first "networks", every parameter no component claims
        (with the optimizer's own options), then the groups the components name (``Encoding.parameter_groups``
        of every encoding in the renderer, merged by name across the networks' copies: the hash tables', without
        weight decay), each where it is not empty. Each group holds its parameters in ``parameters()``' order,
        so that an optimizer's state is laid out as it always was and earlier checkpoints resume."""
        options: dict[str, dict] = {}
        group_of: dict[int, str] = {}  # id(parameter) -> the name of the group a component put it in
        for module in self.grouped_modules():
            for name, group in module.parameter_groups().items():
                own = {key: value for key, value in group.items() if key != "params"}
                if options.setdefault(name, own) != own:
                    raise ValueError(f"parameter group {name!r}: {type(module).__name__} asks for {own}, "
                                     f"another encoding for {options[name]}")
                group_of.update((id(p), name) for p in group["params"])
        groups = {"networks": {"params": []}, **{name: {"params": [], **own} for name, own in options.items()}}
        for parameter in self.parameters():
            groups[group_of.get(id(parameter), "networks")]["params"].append(parameter)
        return {name: group for name, group in groups.items() if name == "networks" or group["params"]}

    def configure_optimizers(self):
        optimizer = self.optimizer(self.parameter_groups())
        base_lr = optimizer.param_groups[0]["lr"]
        max_steps = self.trainer.max_steps
        if max_steps is None or max_steps < 1:
            raise ValueError("trainer.max_steps: expected a positive number of steps (the learning-rate "
                             f"schedule spans them), got {max_steps}")
        ratio, warmup = self.lr_final / base_lr, self.lr_warmup_steps

        def factor(step: int) -> float:
            return warmup_exponential_decay(step, max_steps, ratio, warmup)

        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, self.group_schedules(factor, max_steps))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    # Components beside the renderer: the pose correction (camera_opt), the encodings' progress through training

    def grouped_modules(self) -> list[nn.Module]:
        """The components that name their own parameter groups (``parameter_groups()``): the renderer's encodings,
        then the pose correction where the cameras are refined."""
        encodings = [m for m in self.renderer.modules() if isinstance(m, Encoding)]
        return encodings + ([] if self.camera_opt is None else [self.camera_opt])

    def group_schedules(self, factor: Callable[[int], float],
                        max_steps: int) -> Callable[[int], float] | list[Callable[[int], float]]:
        """The learning-rate schedule (the factor on each group's rate at a step): ``factor``, the optimizer's, for
        every group; where the cameras are refined, one per group (``named_parameter_groups``' order), the pose
        correction's group following its own (``PoseCorrection.lr_factor``: the same formula with its own rates and
        warm-up)."""
        correction = self.camera_opt
        if correction is None:
            return factor

        def pose_factor(step: int) -> float:
            return correction.lr_factor(step, max_steps)
        return [pose_factor if name == correction.GROUP else factor for name in self.named_parameter_groups()]

    def build_camera_opt(self, n_views: int) -> None:
        """Build the pose correction (``camera_opt``, all zero) for ``n_views`` training views."""
        self.camera_opt = self.pose_correction_of(n_views)

    def configure_model(self) -> None:
        """Where the cameras are refined, the pose correction is built with the number of training views (the data
        module's) before Lightning restores a checkpoint or builds the optimizer."""
        if self.pose_correction_of is not None and self.camera_opt is None:
            self.build_camera_opt(len(self.trainer.datamodule.train_views()))

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Where the cameras are refined and the correction is not built yet (a run read back to render:
        ``nerfexp.products.trained.load_module`` calls this before loading the weights), it is built with as many
        views as the checkpoint's correction holds. An earlier nerfexp's weight names are made current first
        (``nerfexp.rundir.trained.current_weights``: its proposal networks, now the sampler's)."""
        current_weights(checkpoint["state_dict"])
        delta = checkpoint["state_dict"].get("camera_opt.delta")
        if self.pose_correction_of is not None and self.camera_opt is None and delta is not None:
            self.build_camera_opt(len(delta) + 1)
        codes = checkpoint["state_dict"].get("renderer.appearance.codes")
        if self.renderer.appearance is not None and codes is not None:  # as many appearance codes as it holds
            self.renderer.appearance.set_views(len(codes))

    def step_batch(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The training batch as this step renders it, and the encodings told how far training is (``Encoding.
        set_progress``: BARF's coarse-to-fine window): where the cameras are refined, each ray turned and moved by
        its view's ("view" [B]) correction, the world view directions ("viewdirs") turned with it."""
        progress = self.global_step / self.trainer.max_steps
        for module in self.renderer.modules():
            if isinstance(module, Encoding):
                module.set_progress(progress)
        if self.camera_opt is None:
            return batch
        origins, directions, viewdirs = self.camera_opt(batch["origins"], batch["directions"], batch["view"],
                                                        batch.get("viewdirs"))
        return {**batch, "origins": origins, "directions": directions, "viewdirs": viewdirs}


def camera_ball(centres: Tensor) -> tuple[Tensor, float]:
    """The ball around camera ``centres`` [N, 3]: their centroid [3] (float64) and the distance of the farthest
    from it (a single camera: 1, the unit the scene is in)."""
    centres = centres.double()
    centre = centres.mean(0)
    radius = float(torch.linalg.vector_norm(centres - centre, dim=-1).max())
    return centre, radius if radius > 0 else 1.0


def regularizer_sums(outputs: dict[str, dict]) -> dict[str, Tensor]:
    """Each regularizer of the networks' ``outputs`` (their ``regularizers``: proposal losses, Ref-NeRF's
    normal penalties), weighted already, summed over the networks that have it."""
    sums: dict[str, Tensor] = {}
    for out in outputs.values():
        for name, value in out.get("regularizers", {}).items():
            sums[name] = sums[name] + value if name in sums else value
    return sums


def check_compiler() -> None:
    """A ConfigError unless torch.compile can build kernels here: on a machine without a GPU its
    inductor backend compiles C++, which needs a compiler (``$CXX``, g++ or clang++) on the PATH."""
    if torch.cuda.is_available() or any(shutil.which(c) for c in (os.environ.get("CXX", "g++"), "g++", "clang++")):
        return
    raise ConfigError("model.compile=true: torch.compile builds C++ kernels on CPUs and no C++ compiler (g++, "
                      "clang++ or $CXX) is on the PATH; install one or set model.compile=false")


@contextlib.contextmanager
def seeded_random(seed: int | None, device: torch.device) -> Iterator[None]:
    """Inside the block torch's global random numbers (CPU, and ``device`` if it is a CUDA device) come
    from a stream seeded with ``seed``; the previous states are restored after it. ``None``: the global
    stream, untouched."""
    if seed is None:
        yield
        return
    cuda = device.type == "cuda"
    with torch.random.fork_rng(devices=[device] if cuda else []):
        # the forked generators only: torch.manual_seed would also seed every other device kind's, at a
        # cost (a stack trace recorded for each lazily seeded kind) of several percent of a small step
        torch.random.default_generator.manual_seed(seed)
        if cuda:
            with torch.cuda.device(device):
                torch.cuda.manual_seed(seed)
        yield
