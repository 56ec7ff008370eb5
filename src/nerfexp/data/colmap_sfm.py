"""COLMAP run through pycolmap: a sparse model found (``find_model``: the user's own, or nerfexp's cache) or
made (``reconstruct``: SIFT features, exhaustive or sequential matching, incremental mapping with one
shared camera), with progress, under ``DIR/colmap`` built atomically (what the scene makes of the model,
its lenses included, and the conventions: ``nerfexp.data.colmap``)."""


import contextlib
import logging
import math
from collections.abc import Iterator
from pathlib import Path

import pycolmap
from tqdm import tqdm

from nerfexp.cpus import available_cpus, capped_line
from nerfexp.data.views import IMAGE_SUFFIXES
from nerfexp.errors import DatasetError
from nerfexp.files import atomic_directory
from nerfexp.geometry.lenses import PARAMETERS
from nerfexp.reading import name_problem

log = logging.getLogger(__name__)

CACHE = "colmap"  # DIR/colmap: nerfexp's own database and sparse model
MODEL_FILES = ("cameras", "images", "points3D")
MATCHERS = ("exhaustive", "sequential")
SEED = 0  # COLMAP's random choices (RANSAC, the mapper's initial pairs) are seeded: the same images give the same model
ADVICE = ("try more overlap between neighbouring views (60-80%), more texture (plain walls, sky, glass and "
          "reflections give no features), sharper images, more features (data.max_features), "
          "data.matcher=exhaustive, or a camera model that fits the lens (data.camera_model=OPENCV for wide angles)")


def image_files(folder: Path) -> list[str]:
    """Names of the images below ``folder`` as COLMAP gives them (relative POSIX paths), sorted."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                  if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file() and not p.name.startswith("."))


def is_model(path: Path) -> bool:
    """Whether ``path`` holds a COLMAP sparse model, binary or text."""
    return any(all((path / f"{name}{ext}").is_file() for name in MODEL_FILES) for ext in (".bin", ".txt"))


def find_model(root: Path) -> Path | None:
    """The sparse model to use for the scene ``root``: the user's, else nerfexp's cache, else None."""
    for path in (root / "sparse" / "0", root / "sparse", root / CACHE / "sparse" / "0"):
        if is_model(path):
            return path
    return None


def read_model(path):
    """A ``pycolmap.Reconstruction`` read from the folder ``path`` (binary or text files), its images' names
    checked (``check_image_names``)."""
    path = Path(path)
    if not is_model(path):
        raise DatasetError(f"{path} holds no COLMAP sparse model: expected cameras, images and points3D, "
                           f"all .bin or all .txt")
    try:
        reconstruction = pycolmap.Reconstruction(path)
    except Exception as error:  # pycolmap raises plain exceptions for malformed files
        raise DatasetError(f"{path}: cannot read the COLMAP model ({error})") from None
    check_image_names(reconstruction, path)
    return reconstruction


def check_image_names(reconstruction, path: Path) -> None:
    """A DatasetError naming the model ``path`` and the image whose name (a file's path below the images' folder)
    no file can have: text that is not UTF-8 (pycolmap decodes names strictly), a NUL byte or a lone surrogate
    (``nerfexp.reading.name_problem``). Names are the paths nerfexp opens: checked once, where the model is read."""
    for image_id, image in reconstruction.images.items():
        try:
            name = image.name
        except UnicodeDecodeError as error:
            raise DatasetError(f"{path}: image {image_id}: its name is not UTF-8 text ({error.reason} at byte "
                               f"{error.start})") from None
        if (problem := name_problem(name)) is not None:
            raise DatasetError(f"{path}: image {image_id}: its name {problem}, got {name!r:.80}")


@contextlib.contextmanager
def _colmap_log_level(verbose: bool) -> Iterator[None]:
    """COLMAP's own log (glog, on stderr) at INFO with ``verbose``, else warnings and errors only."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def check_camera_model(name: str) -> None:
    """A DatasetError unless ``name`` is a COLMAP camera model whose lens nerfexp reads
    (``nerfexp.geometry.lenses.PARAMETERS``)."""
    if name not in PARAMETERS:
        raise DatasetError(f"unsupported camera model {name!r} (data.camera_model): nerfexp reads the lenses of "
                           f"{', '.join(PARAMETERS)}")


def registered_enough(n_registered: int, n_images: int, min_registered: float, where: str) -> None:
    """A DatasetError unless at least max(2, ceil(min_registered n_images)) images were registered."""
    needed = max(2, math.ceil(min_registered * n_images))
    if n_registered < needed:
        raise DatasetError(f"COLMAP registered {n_registered} of {n_images} images of {where} (at least {needed} "
                           f"needed, data.min_registered={min_registered:g}); {ADVICE}")


def effective_threads(threads: int, cpus: int) -> int:
    """The number of threads COLMAP runs for ``threads`` (``data.threads``) on ``cpus`` CPUs: ``threads`` itself, at
    most ``cpus`` (``nerfexp.cpus``), or all of them where it is <= 0 (-1: every CPU this process may use, where
    COLMAP's own -1 would take every core of the machine, whatever the process's affinity).

    >>> effective_threads(-1, 4), effective_threads(2, 4), effective_threads(64, 4)
    (4, 2, 4)
    """
    return min(threads, cpus) if threads > 0 else cpus


def colmap_threads(threads: int) -> int:
    """``effective_threads`` on the CPUs this process may use, logging the line that says where a count asked for
    above them is capped (``nerfexp.cpus.capped_line``)."""
    cpus = available_cpus()
    if (line := capped_line(f"data.threads={threads}", threads, cpus)) is not None:
        log.warning("%s", line)
    return effective_threads(threads, cpus)


def shared_camera_id(database: Path) -> int:
    """The id of the first camera in the COLMAP ``database``; -1 where it has none."""
    with pycolmap.Database.open(database) as db:
        return min((camera.camera_id for camera in db.read_all_cameras()), default=-1)


def extract_features(database: Path, image_dir: Path, names: list[str], camera_model: str = "SIMPLE_RADIAL",
                     max_features: int = 4096, threads: int = 1) -> None:
    """SIFT features (on the CPU, at most ``max_features`` per image, on ``threads`` threads: ``colmap_threads``) of
    the images ``names`` of ``image_dir`` into ``database``, one ``camera_model`` camera shared by all, with a
    progress bar counting images.

    pycolmap reports nothing while it extracts, so the images go in batches, one call each, and the bar
    moves after each batch. Each thread extracts whole images, so a batch holds two per thread: every
    thread has work, one that finishes early takes a second image while the batch's slowest finishes,
    and each call's fixed cost is shared by twice the images (one image per call forgoes the threads).
    The first batch makes the shared camera (CameraMode.SINGLE) and the later ones name it
    (``existing_camera_id``), so the database is the one a single call over all the images makes.
    """
    # an explicit count: with -1 COLMAP warns once per call (per batch) that it uses every core
    extraction = pycolmap.FeatureExtractionOptions(num_threads=threads, use_gpu=False)
    extraction.sift.max_num_features = max_features
    reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
    batch_size = 2 * threads
    with tqdm(total=len(names), desc="COLMAP features", unit="image", disable=None) as bar:
        for start in range(0, len(names), batch_size):
            batch = names[start:start + batch_size]
            pycolmap.extract_features(database, image_dir, batch, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            if reader.existing_camera_id < 0:
                reader.existing_camera_id = shared_camera_id(database)
            bar.update(len(batch))


def reconstruct(root, camera_model: str = "SIMPLE_RADIAL", matcher: str = "exhaustive", max_features: int = 4096,
                threads: int = -1, min_registered: float = 0.8, verbose: bool = False,
                image_dir: Path | None = None) -> Path:
    """Run COLMAP on the images of ``image_dir`` (None: ``root/images``) into ``root/colmap`` and return
    the sparse model's folder.

    Features (``extract_features``: SIFT on the CPU, at most ``max_features`` per image, one
    ``camera_model`` camera shared by all images, a progress bar over the images), then matching
    (``exhaustive`` or ``sequential``) and incremental mapping, each a step of a second bar
    (``verbose``: COLMAP's own log too). ``threads``: ``colmap_threads``' (-1: every CPU this process may use).
    COLMAP's random choices are seeded (``SEED``), so that a reconstruction does not depend on the draw (with
    several threads their order may still differ). Raises a DatasetError, and keeps nothing, when fewer than
    ``min_registered`` of the images are registered.
    """
    root = Path(root)
    image_dir = root / "images" if image_dir is None else Path(image_dir)
    names = image_files(image_dir)
    if not names:
        raise DatasetError(f"{image_dir} holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    check_camera_model(camera_model)
    if matcher not in MATCHERS:
        raise DatasetError(f"unknown matcher {matcher!r} (data.matcher): expected one of {', '.join(MATCHERS)}")
    cache = root / CACHE
    if cache.exists():
        raise DatasetError(f"{cache} exists but holds no sparse model in sparse/0; move it away (nerfexp never "
                           f"deletes it) to reconstruct the scene again")
    threads = colmap_threads(threads)
    with _colmap_log_level(verbose), atomic_directory(cache) as work:
        pycolmap.set_random_seed(SEED)
        database = work / "database.db"
        extract_features(database, image_dir, names, camera_model, max_features, threads)
        with tqdm(total=2, desc="COLMAP", unit="stage", disable=None) as bar:
            bar.set_postfix_str(f"{matcher} matching")
            matching = pycolmap.FeatureMatchingOptions(num_threads=threads, use_gpu=False)
            match = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
            match(database, matching_options=matching, device=pycolmap.Device.cpu)
            bar.update()
            bar.set_postfix_str("incremental mapping")
            options = pycolmap.IncrementalPipelineOptions(num_threads=threads, multiple_models=False,
                                                          random_seed=SEED)
            models = pycolmap.incremental_mapping(database, image_dir, work / "sparse", options)
            bar.update()
        n_registered = max((m.num_reg_images() for m in models.values()), default=0)
        registered_enough(n_registered, len(names), min_registered, image_dir)
        if not is_model(work / "sparse" / "0"):
            raise DatasetError(f"COLMAP wrote no model for {image_dir} to {work / 'sparse' / '0'}")
    return cache / "sparse" / "0"
