"""The LightningModule: trains a ``VolumeRenderer`` on ray batches and scores whole images."""

import contextlib
from collections.abc import Callable, Iterator

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.metrics import psnr, ssim
from nerfexp.renderer import VolumeRenderer, final_output


class NeRFModule(L.LightningModule):
    """Loss = sum over networks of the MSE of their colours (coarse + fine); Adam whose learning
    rate decays exponentially from the optimizer's ``lr`` to ``lr_final`` over ``trainer.max_steps``,
    ramped up linearly over the first ``lr_warmup_steps`` (0: none, as in the paper).

    Evaluation renders whole images in chunks of ``chunk`` rays (memory bounded at any resolution)
    and scores the fine network's image (the only one without hierarchy).

    ``diagnostics`` holds what the latest training batch showed of each network, detached (no graph,
    no copy): ``{"coarse": {"loss": [], "opacity": [B]}, "fine": {...}}`` (only "coarse" without
    hierarchy), the colour loss and the rendered opacity of each of the B rays. Callbacks read it
    between the backward pass and the optimizer step (``nerfexp.guards.TrainingGuard``), which
    ``training_step``'s return value does not reach, and at no cost of extra rendering.
    """

    def __init__(self, renderer: VolumeRenderer, optimizer: Callable[..., torch.optim.Optimizer],
                 lr_final: float, chunk: int = 8192, lr_warmup_steps: int = 0):
        super().__init__()
        self.renderer, self.optimizer, self.lr_final, self.chunk = renderer, optimizer, lr_final, chunk
        self.lr_warmup_steps = lr_warmup_steps
        self.diagnostics: dict[str, dict[str, Tensor]] = {}

    @property
    def networks(self) -> dict[str, nn.Module]:
        """The renderer's networks under the names its outputs use: coarse and fine, or coarse alone."""
        return {name: net for name in ("coarse", "fine") if (net := getattr(self.renderer, name)) is not None}

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """One step on ``batch``; its stratified jitter is drawn from ``batch["seed"]`` where the batch
        has one (``RandomRays``), so that the step is a function of the batch and the weights alone."""
        with seeded_random(batch.get("seed"), self.device):
            outputs = self.renderer(batch["origins"], batch["directions"], deterministic=False,
                                    viewdirs=batch.get("viewdirs"))
        losses = {name: F.mse_loss(out["rgb"], batch["rgb"]) for name, out in outputs.items()}
        self.diagnostics = {name: {"loss": losses[name].detach(), "opacity": out["opacity"].detach()}
                            for name, out in outputs.items()}
        loss = sum(losses.values())
        final = final_output(losses)
        self.log("train/loss", loss, prog_bar=True)
        self.log("train/psnr", -10 * torch.log10(final.detach()), prog_bar=True)
        self.log("train/lr", self.optimizers().param_groups[0]["lr"])
        return loss

    @torch.no_grad()
    def render_image(self, origins: Tensor, directions: Tensor, viewdirs: Tensor | None = None) -> dict[str, Tensor]:
        """Deterministic render of rays [H, W, 3] (``viewdirs`` [H, W, 3] optional, see ``VolumeRenderer``)
        in chunks: ``rgb`` [H, W, 3], ``depth``, ``opacity`` [H, W]."""
        H, W, _ = origins.shape
        flat_o, flat_d = origins.reshape(-1, 3), directions.reshape(-1, 3)
        flat_v = None if viewdirs is None else viewdirs.reshape(-1, 3)
        parts = []
        for start in range(0, H * W, self.chunk):
            chunk = slice(start, start + self.chunk)
            outputs = self.renderer(flat_o[chunk], flat_d[chunk], deterministic=True,
                                    viewdirs=None if flat_v is None else flat_v[chunk])
            final = final_output(outputs)
            parts.append({key: final[key] for key in ("rgb", "depth", "opacity")})
        return {key: torch.cat([p[key] for p in parts]).reshape(H, W, *parts[0][key].shape[1:])
                for key in parts[0]}

    def _evaluate(self, batch: dict, split: str) -> dict:
        image = self.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))
        scores = {"psnr": psnr(image["rgb"], batch["rgb"]), "ssim": ssim(image["rgb"], batch["rgb"])}
        for name, value in scores.items():
            self.log(f"{split}/{name}", value, batch_size=1)
        return {"index": int(batch["index"]), "target": batch["rgb"], **image, **scores}

    def validation_step(self, batch: dict, batch_idx: int) -> dict:
        return self._evaluate(batch, "val")

    def test_step(self, batch: dict, batch_idx: int) -> dict:
        return self._evaluate(batch, "test")

    def configure_optimizers(self):
        optimizer = self.optimizer(self.parameters())
        base_lr = optimizer.param_groups[0]["lr"]
        max_steps = self.trainer.max_steps
        if max_steps is None or max_steps < 1:
            raise ValueError("trainer.max_steps: expected a positive number of steps (the learning-rate "
                             f"schedule spans them), got {max_steps}")
        ratio, warmup = self.lr_final / base_lr, self.lr_warmup_steps

        def factor(step: int) -> float:
            ramp = min((step + 1) / warmup, 1.0) if warmup > 0 else 1.0
            return ramp * ratio ** min(step / max_steps, 1.0)

        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}


@contextlib.contextmanager
def seeded_random(seed: int | None, device: torch.device) -> Iterator[None]:
    """Inside the block torch's global random numbers (CPU, and ``device`` if it is a CUDA device) come
    from a stream seeded with ``seed``; the previous states are restored after it. ``None``: the global
    stream, untouched."""
    if seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(seed)
        yield


def flushes_denormals() -> bool:
    """Whether this thread's CPU arithmetic flushes float32 denormals to zero (torch sets it, but has no getter)."""
    return (torch.tensor(torch.finfo(torch.float32).tiny) / 2).item() == 0.0


class FlushDenormals(L.Callback):
    """Flushes CPU denormals to zero while ``fit`` runs, and puts the previous setting back after it,
    also when it fails.

    exp(-optical depth) behind surfaces and the densities of empty space produce float32 denormals
    (below 1.2e-38), which made the CPU's backward pass about 1.8x slower (0.173 vs 0.097 s per step at
    scale=cpu, identical results); flushing them costs nothing in accuracy at these magnitudes. The
    setting is process-wide, so it is scoped to training: other code in the process (a notebook, the
    test suite's float64 references) keeps IEEE denormals.
    """

    def __init__(self):
        self._previous: bool | None = None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._previous = flushes_denormals()
        torch.set_flush_denormal(True)

    def _restore(self) -> None:
        if self._previous is not None:
            torch.set_flush_denormal(self._previous)
            self._previous = None

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore()
