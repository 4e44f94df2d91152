"""The unseen-ground campaign's fixture piles and its command line."""

import math

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from tools.unseen_campaign import REPOSE_SLOPE, fixture_piles, heightfield_pile, main


def test_that_the_corner_fixture_is_a_quarter_cone_of_its_stated_size():
    storage = Storage()
    shape = fixture_piles(storage)["corner"]
    pile = heightfield_pile(shape, storage, "corner")
    radius = shape.peak_m / REPOSE_SLOPE
    assert pile.volume_m3 == pytest.approx(math.pi * radius**2 * shape.peak_m / 3 / 4, rel=0.01)


def test_that_the_wall_end_fixture_leaves_both_corners_bare():
    storage = Storage()
    shape = fixture_piles(storage)["wall-end"]
    assert shape.height_m(np.array([0.0, 0.0]), np.array([0.0, storage.width_m])).max() == 0.0
    assert shape.height_m(np.array([0.0]), np.array([storage.width_m / 2]))[0] == pytest.approx(shape.peak_m)


@pytest.mark.parametrize("argv", [["--piles", "pyramid"], ["--positions", "0"], ["--positions", "21"]])
def test_that_bad_arguments_are_refused_with_one_line(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("unseen_campaign:") and "\n" not in err


def test_that_the_campaign_rewrites_its_own_section_and_keeps_the_rest_of_the_page(tmp_path, monkeypatch):
    """docs/unseen.md also holds the floor-out-of-reach prose and `tools.echo_check`'s section: a campaign run
    replaced the whole page once and lost them."""
    import tools.unseen_campaign as uc

    monkeypatch.setattr(uc, "markdown_text", lambda rows, policies, command: f"tables of {command}")
    page = tmp_path / "unseen.md"
    uc.write_markdown([], page, (), "run 1")
    assert page.read_text().startswith(uc.TITLE) and "tables of run 1" in page.read_text()
    page.write_text(page.read_text() + "\n## Other\n\nprose\n\n<!-- echo-check:start -->\nx\n<!-- echo-check:end -->\n")
    uc.write_markdown([], page, (), "run 2")
    text = page.read_text()
    assert "tables of run 2" in text and "tables of run 1" not in text
    assert text.index("tables of run 2") < text.index("## Other") and "<!-- echo-check:start -->\nx" in text
