"""A report as a web page that opens from disk: ``report.md`` as HTML, the plots, and test views rendered
by each variant side by side with the ground truth.

The page loads nothing from elsewhere: its style is inline, its pictures are files in its own folder,
and its Content-Security-Policy lets it load only those (no scripts at all, no fonts, no network), so a
label taken from someone else's run directory cannot run as code. The Markdown is converted by
Python-Markdown with raw HTML, links and images turned off: a ``<`` or a link in a label is shown, not
parsed.
"""

import html
from dataclasses import dataclass

import markdown

POLICY = "default-src 'none'; img-src 'self' file: data:; style-src 'unsafe-inline'"
PICTURE_WIDTH = 192  # CSS pixels of each picture; smaller images are enlarged with visible pixels

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; max-width: 1600px; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: left; }
th { background: #f3f3f3; }
code { background: #f3f3f3; padding: 0 0.2em; }
.plots img { max-width: 48%; margin-right: 1%; border: 1px solid #ddd; }
.tiles { display: flex; flex-wrap: wrap; gap: 1em; align-items: flex-start; }
.tile { margin: 0; width: PICTURE_WIDTHpx; font-size: 0.85em; overflow-wrap: anywhere; }
.tile img { display: block; width: PICTURE_WIDTHpx; height: auto; margin-bottom: 2px; }
.tile img.enlarged { image-rendering: pixelated; }
.missing { width: PICTURE_WIDTHpx; height: 4em; background: #f3f3f3; color: #777; display: flex;
           align-items: center; justify-content: center; margin-bottom: 2px; }
""".replace("PICTURE_WIDTH", str(PICTURE_WIDTH))


@dataclass(frozen=True)
class Picture:
    """An image file of the page's folder (``src``: its path relative to the page, with its pixel
    ``width``), or where it is missing (``src`` None) the reason."""

    alt: str
    src: str | None = None
    width: int = 0
    missing: str = ""


@dataclass(frozen=True)
class Tile:
    """One variant's pictures of a test view (its render and error image, or the ground truth), with a
    title and a caption line (the view's PSNR and SSIM)."""

    title: str
    pictures: tuple[Picture, ...]
    caption: str = ""


MARKUP_FROM_TEXT = ("html", "entity", "reference", "link", "image_link", "image_reference", "short_reference",
                    "short_image_ref", "autolink", "automail")  # inline patterns a report never writes


def markdown_html(text: str) -> str:
    """``text`` (Markdown with tables, code spans and emphasis: what ``nerfexp.report.tables.markdown`` writes) as
    HTML. Raw HTML, entities, links and images in it are shown as the text they are: a report has none of
    its own, so any there came from a run's label."""
    converter = markdown.Markdown(extensions=["tables"])
    converter.preprocessors.deregister("html_block")
    for pattern in MARKUP_FROM_TEXT:
        converter.inlinePatterns.deregister(pattern)
    return converter.convert(text)


def picture_html(picture: Picture) -> str:
    if picture.src is None:
        return f'<div class="missing">{html.escape(picture.missing)}</div>'
    enlarged = ' class="enlarged"' if picture.width < PICTURE_WIDTH else ""
    return f'<img src="{html.escape(picture.src)}" alt="{html.escape(picture.alt)}"{enlarged}>'


def tile_html(tile: Tile) -> str:
    pictures = "".join(picture_html(p) for p in tile.pictures)
    caption = f"<br>{html.escape(tile.caption)}" if tile.caption else ""
    return (f'<figure class="tile">{pictures}<figcaption><b>{html.escape(tile.title)}</b>{caption}'
            "</figcaption></figure>")


def page_html(report_md: str, plots: list[tuple[str, str]], views: dict[int, list[Tile]], views_note: str) -> str:
    """The whole page: ``report_md`` converted, its first section (the table) first; then for each test
    view (index -> tiles) a row of tiles, after ``views_note`` saying what they show; then the ``plots``
    (file, description); then the rest of ``report_md`` (from its first ``##`` heading)."""
    first, heading, rest = report_md.partition("\n## ")
    body = [markdown_html(first), "<h2>Test views</h2>", f"<p>{html.escape(views_note)}</p>"]
    for index, tiles in views.items():
        body += [f"<h3>Test view {index}</h3>", '<div class="tiles">', *map(tile_html, tiles), "</div>"]
    body += ["<h2>Plots</h2>", '<div class="plots">']
    body += [f'<img src="{html.escape(src)}" alt="{html.escape(alt)}">' for src, alt in plots]
    body += ["</div>", markdown_html(heading.lstrip("\n") + rest)]
    return ("<!doctype html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f'<meta http-equiv="Content-Security-Policy" content="{POLICY}">\n'
            f"<title>nerfexp report</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")
