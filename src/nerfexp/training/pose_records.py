"""What camera refinement (``camera_opt``) leaves in a run: the training cameras as refined, written when training
ends to ``RUN_DIR/cameras/train_poses.json`` (``nerfexp.rundir.layout.REFINED_POSES``), which the commands that
read a run back use for its training cameras (``nerfexp.products.trained.RefinedScene``).

The file, JSON data: ``c2w`` (the refined cameras, [N][4][4], OpenGL convention as every nerfexp camera),
``initial_c2w`` (the cameras training started from), ``gauge`` (what fixes the frame), ``step``, and
``pose_noise`` with ``errors`` where training poses were perturbed by known amounts (``datamodule.pose_noise``):
the rotation and centre errors against the true poses after aligning the centres by a similarity
(``nerfexp.geometry.alignment.pose_errors``), ``before`` and ``after`` refinement.
"""

import json
import logging
from pathlib import Path

import lightning as L
from torch import Tensor

from nerfexp import manifest
from nerfexp.geometry.alignment import pose_errors
from nerfexp.rundir.layout import REFINED_POSES

log = logging.getLogger("nerfexp")

GAUGE = "view 0 pinned: its correction is zero, so the frame is that of the first training camera"


def pose_record(initial: Tensor, refined: Tensor, true: Tensor | None, pose_noise: tuple | None,
                step: int) -> dict:
    """The file's contents (the module's docstring) for cameras ``initial`` and ``refined`` [N, 4, 4], and the
    ``true`` ones where known. ``errors`` needs at least 3 cameras not all at one place (else null)."""
    errors = None
    if true is not None and len(true) >= 3:
        errors = {"before": pose_errors(initial, true), "after": pose_errors(refined, true)}
    return {"c2w": refined.double().tolist(), "initial_c2w": initial.double().tolist(), "gauge": GAUGE,
            "step": step, "pose_noise": None if pose_noise is None else list(pose_noise), "errors": errors}


class RefinedPoses(L.Callback):
    """When training ends, global rank 0 writes the module's refined training cameras (its ``camera_opt``) into
    ``output_dir`` (``pose_record``) and says how far they moved toward the truth where it is known."""

    def __init__(self, output_dir: str | Path):
        self.output_dir = Path(output_dir)

    def on_train_end(self, trainer: L.Trainer, module: L.LightningModule) -> None:
        if module.camera_opt is None or not trainer.is_global_zero:
            return
        datamodule = trainer.datamodule
        initial = datamodule.train_views().c2w
        record = pose_record(initial, module.camera_opt.refined(initial.to(module.device)).cpu(),
                             datamodule.true_train_poses, datamodule.pose_noise, trainer.global_step)
        manifest.write(self.output_dir, REFINED_POSES.as_posix(), json.dumps(record, indent=1).encode())
        if record["errors"] is not None:
            before, after = record["errors"]["before"], record["errors"]["after"]
            log.info("camera_opt: training poses after alignment, rotation %.3f -> %.3f deg, centre %.4g -> %.4g "
                     "(%s)", before["rotation_deg"], after["rotation_deg"], before["centre"], after["centre"],
                     REFINED_POSES)
