"""A lens as JSON keys, nerfstudio's (``transforms.json``): ``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy``
(pixels) and the model's coefficients. nerfexp writes them in its camera files (a render's ``cameras.json``)
and reads them there and in nerfstudio's data format (``nerfexp.data.transforms_file``).

Models (``RECORD_MODELS``): ``PINHOLE``; ``OPENCV`` (``k1 k2 p1 p2``, and ``k3`` where present);
``OPENCV_FISHEYE`` (``k1 k2 k3 k4``); and ``FULL_OPENCV`` (``k1 .. k6 p1 p2``, OpenCV's rational model,
which nerfstudio does not write: nerfexp writes it for a COLMAP camera of that model). Coefficients left
out are 0. nerfstudio's ``OPENCV`` also has a ``k4`` (an r^8 term of its own); nerfexp refuses a nonzero one.
"""

import torch

from nerfexp.domains import is_real
from nerfexp.geometry.lenses import SLOTS, Intrinsics, distortion_vector

RECORD_MODELS = {
    "PINHOLE": (),
    "OPENCV": ("k1", "k2", "k3", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
}
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")
FOCAL_RANGE = (2.0 ** -24, 2.0 ** 24)  # a focal length in pixels: float32 directions stay finite and resolved
COEFFICIENT_LIMIT = 1e6  # the largest distortion coefficient read (real lenses have |k| < 10)


class LensRecordError(ValueError):
    """A lens record's key is missing or holds a value out of its range: ``key`` and what was expected."""

    def __init__(self, key: str, message: str):
        super().__init__(f"'{key}': {message}")
        self.key = key


def record_model(lens: Intrinsics) -> str:
    """The ``RECORD_MODELS`` name that holds one lens (shape []): the simplest whose coefficients cover it."""
    if bool(lens.fisheye):
        return "OPENCV_FISHEYE"
    used = {name for name, value in zip(SLOTS, lens.distortion.tolist()) if value != 0}
    return next(model for model in ("PINHOLE", "OPENCV", "FULL_OPENCV") if used <= set(RECORD_MODELS[model]))


def lens_record(lens: Intrinsics) -> dict:
    """The JSON keys of one lens (shape []): ``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy`` and the
    model's coefficients (``RECORD_MODELS``)."""
    model = record_model(lens)
    named = dict(zip(SLOTS, lens.distortion.tolist()))
    return {"camera_model": model, **dict(zip(INTRINSIC_KEYS, lens.params.tolist())),
            **{name: named[name] for name in RECORD_MODELS[model]}}


def read_lens_record(fields: dict, defaults: dict | None = None) -> Intrinsics:
    """The lens (shape []) of the JSON keys ``fields`` (``lens_record``'s), a key missing from ``fields``
    taken from ``defaults`` (a file's top-level keys, where a frame may override them); ``camera_model``
    missing: ``PINHOLE``. A ``LensRecordError`` names the first key that is missing, of the wrong type, out
    of range (focal lengths in ``FOCAL_RANGE``, coefficients within ``COEFFICIENT_LIMIT``) or not used by
    the model (a nonzero ``k4`` on ``OPENCV``, a coefficient of another model)."""
    merged = {**(defaults or {}), **fields}
    model = merged.get("camera_model", "PINHOLE")
    if not (isinstance(model, str) and model in RECORD_MODELS):
        raise LensRecordError("camera_model", f"expected one of {', '.join(RECORD_MODELS)}, got {model!r:.80}")
    for key in INTRINSIC_KEYS:
        if key not in merged:
            raise LensRecordError(key, "missing: expected a number of pixels")
        value = merged[key]
        low, high = FOCAL_RANGE if key.startswith("fl_") else (-FOCAL_RANGE[1], FOCAL_RANGE[1])
        if not (is_real(value) and low <= value <= high):
            raise LensRecordError(key, f"expected a number of pixels in [{low:.3g}, {high:.3g}], got {value!r:.80}")
    coefficients = {}
    for name in SLOTS:
        value = merged.get(name, 0.0)
        if not (is_real(value) and abs(value) <= COEFFICIENT_LIMIT):
            raise LensRecordError(name, f"expected a finite number within +-{COEFFICIENT_LIMIT:g}, got {value!r:.80}")
        if value != 0 and name not in RECORD_MODELS[model]:
            raise LensRecordError(name, f"camera_model {model} has no coefficient {name} (it has "
                                        f"{', '.join(RECORD_MODELS[model]) or 'none'}), got {value!r}")
        coefficients[name] = value
    params = torch.tensor([float(merged[key]) for key in INTRINSIC_KEYS], dtype=torch.float64)
    return Intrinsics(params, distortion_vector(coefficients), torch.tensor(model == "OPENCV_FISHEYE"))
