"""Pictures of benchmark results: images side by side."""

from pathlib import Path

from PIL import Image


def side_by_side(paths: list[Path], out: Path, scale: int = 3) -> None:
    """The images at ``paths`` (of one size) in a row, enlarged ``scale`` times without smoothing, saved to ``out``."""
    images = [Image.open(path).convert("RGB") for path in paths]
    width, height = images[0].size
    sheet = Image.new("RGB", (width * len(images), height), "white")
    for k, image in enumerate(images):
        sheet.paste(image, (k * width, 0))
    sheet.resize((sheet.width * scale, sheet.height * scale), Image.NEAREST).save(out)
