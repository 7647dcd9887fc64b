"""scripts/reliability_corpus.py: every in-process case of issue 57's corpus ends as it should (exit 2 and one
``error:`` line, or exit 0; no traceback; nothing half-written). Cases another item of issue 57 fixes are
``pending``: reported, not failed. The subprocess cases (signals, two writers, bombs) run with the script itself."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "reliability_corpus.py"


def _corpus():
    spec = importlib.util.spec_from_file_location("reliability_corpus", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve the module's annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def test_the_corpus_has_forty_cases_across_every_kind():
    corpus = _corpus()
    assert len(corpus.CASES) >= 40 and len({c.name for c in corpus.CASES}) == len(corpus.CASES)
    assert {c.kind for c in corpus.CASES} == {"security", "resume", "concurrency", "signals", "disk", "config", "eval"}


def test_every_in_process_case_ends_cleanly(tmp_path):
    corpus = _corpus()
    cases = [c for c in corpus.CASES if not c.process]
    outcomes = corpus.run_cases(cases, tmp_path, echo=False)
    failed = {o.case.name: o.problems for o in outcomes if o.verdict == "FAIL"}
    assert not failed, failed
    assert sum(o.verdict == "ok" for o in outcomes) >= 35
