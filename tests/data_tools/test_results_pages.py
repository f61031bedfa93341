"""The docs' results pages show figures that exist, each with the command that redraws it."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results"
PAGES = sorted(path for path in RESULTS.glob("*.md") if path.name != "index.md")
DOCUMENTS = [ROOT / "README.md", ROOT / "data_tools" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")


def images(document: Path) -> list[str]:
    """The targets of the markdown images in ``document``."""
    return IMAGE.findall(document.read_text())


def test_the_results_pages_are_there():
    names = {path.stem for path in PAGES}
    assert {"scores", "mask", "localization", "tracking", "speed", "paper"} <= names


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda path: str(path.relative_to(ROOT)))
def test_every_image_a_document_shows_exists(document):
    missing = [target for target in images(document) if not (document.parent / target).resolve().is_file()]
    assert not missing, f"{document.relative_to(ROOT)} shows images that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda path: path.stem)
def test_each_results_page_shows_a_figure_and_the_command_that_draws_it(page):
    shown = images(page)
    assert shown, f"{page.relative_to(ROOT)} shows no figure"
    text = page.read_text()
    for target in shown:
        name = Path(target).name
        assert f"docs/images/{name}" in text, f"{page.relative_to(ROOT)} shows {name} without the command that draws it"


def test_every_image_in_the_docs_is_shown_somewhere():
    shown = {(document.parent / target).resolve() for document in DOCUMENTS for target in images(document)}
    unused = [path.name for path in sorted((ROOT / "docs" / "images").iterdir()) if path.resolve() not in shown]
    assert not unused, f"docs/images holds figures no page shows: {unused}"
