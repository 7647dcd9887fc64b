"""The table of kinds in docs/plugins.md is the one generated from occplug.KINDS and the interfaces."""

from __future__ import annotations

from pathlib import Path

import occplug
from occplug.docs import markdown_table, public_name
from occplug.kinds import KINDS

DOCS = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"


def test_the_docs_table_is_the_generated_one():
    assert markdown_table() in DOCS.read_text(), (
        "docs/plugins.md's table of kinds differs from occplug.docs.markdown_table(); paste its output there"
    )


def test_every_kind_has_a_place_a_contract_and_a_public_interface():
    for kind in KINDS.values():
        assert kind.place and kind.contract, f"kind {kind.name} lacks its place or contract"
        name = public_name(kind.interface())
        assert name.startswith((*occplug.PUBLIC_MODULES, "lightning.")), name


def test_the_table_follows_a_changed_given(monkeypatch):
    # the table is read from the interface: widening a kind's given changes it (so the docs test would fail)
    scene = KINDS["scene"].interface()
    monkeypatch.setattr(scene, "given", (*scene.given, "extra_argument"))
    assert "`extra_argument`" in markdown_table()
