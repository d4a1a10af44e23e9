"""docs/cli.md documents every verb of ``plenopiv`` with every option of its parser."""

from __future__ import annotations

import argparse
import re

from conftest import REPO
from plenopiv.cli import build_parser

PAGE = REPO / "docs" / "cli.md"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def verb_options() -> dict[str, set[str]]:
    """``{verb: option strings}`` of every verb, a verb's sub-kinds (simulate's) included."""
    out = {}
    for verb, parser in _subparsers(build_parser()).items():
        options: set[str] = set()
        for p in (parser, *_subparsers(parser).values()):
            options |= {s for a in p._actions for s in a.option_strings}
        out[verb] = options
    return out


def sections(text: str) -> dict[str, str]:
    """The text of each ``## plenopiv VERB`` section of the page."""
    parts = re.split(r"^## plenopiv (\w[\w-]*)\s*$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def test_every_verb_has_a_section_naming_each_of_its_options():
    text = PAGE.read_text()
    found = sections(text)
    verbs = verb_options()
    assert not sorted(set(verbs) - set(found)), "verbs without a section in docs/cli.md"
    for verb, options in verbs.items():
        missing = sorted(o for o in options - {"-h", "--help"}
                         if not re.search(rf"`{re.escape(o)}[` ]", found[verb]))
        assert not missing, f"docs/cli.md, plenopiv {verb}: options not documented: {missing}"
    assert "`--help`" in text and "`-h`" in text and "`plenopiv --version`" in text


def test_the_verb_table_links_every_section():
    text = PAGE.read_text()
    for verb in verb_options():
        assert f"[`{verb}`](#plenopiv-{verb})" in text, verb


def test_calibrate_json_keys_of_the_contract_are_documented():
    section = sections(PAGE.read_text())["calibrate"]
    for key in ("image_distance_mm", "method", "offset_um", "rotation_rad", "rms_residual_px",
                "n_lenslets", "n_missing"):
        assert f"`{key}`" in section, key
