"""Every registered component (built-ins and installed plugins) passes the conformance check."""

import pytest

from occplug.plugins import get_registry
from occplug.testing import check_component, make_tiny_batch
from occplug.testing.conformance import CHECKED_KINDS

# (kind, name) -> why it is not swept here
EXCLUDED = {
    ("encoder", "timm"): "needs the optional timm package; covered by tests/components/test_encoders.py",
}


def entries():
    reg = get_registry()
    return [(e.kind, e.name) for kind in CHECKED_KINDS for e in reg.entries(kind) if (e.kind, e.name) not in EXCLUDED]


@pytest.mark.parametrize(("kind", "name"), entries())
def test_component_conforms(kind, name):
    check_component(kind, name, batch=make_tiny_batch())


def test_every_component_has_a_summary():
    missing = [f"{e.kind}/{e.name}" for e in get_registry().entries() if not e.summary]
    assert not missing, f"components without a docstring summary: {missing}"
