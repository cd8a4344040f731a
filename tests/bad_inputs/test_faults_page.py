"""docs/faults.md promises, each backed by a row of the bad-input tables."""

from __future__ import annotations

import fnmatch
import importlib
import re
from pathlib import Path

from bad_inputs.support import REPO, table

KINDS = sorted(p.stem.removeprefix("test_") for p in Path(__file__).parent.glob("test_*.py")
               if p.stem != "test_faults_page")


def test_faults_page_cites_every_row_and_only_rows():
    """Every ``KIND::ID`` the page cites names a row (or, as ``KIND::*``, some rows) of a table, and every row is
    cited, so neither a promise without a test nor a test without its promise is left."""
    ids = set()
    for kind in KINDS:
        module = importlib.import_module(f"bad_inputs.test_{kind}")
        ids |= {f"{kind}::{r.id}" for r in table(module.__name__)}
    assert len(ids) > 300, "the tables lost their rows"
    doc = (REPO / "docs" / "faults.md").read_text(encoding="utf-8")
    cited = set(re.findall(r"`([a-z_]+::[A-Za-z0-9.=+*-]+)`", doc))
    assert len(cited) > 100, "the citation pattern found almost nothing: has the page's format changed?"
    unknown = sorted(c for c in cited if not fnmatch.filter(ids, c))
    assert not unknown, f"docs/faults.md cites ids that are not rows: {unknown}"
    uncited = sorted(i for i in ids if not any(fnmatch.fnmatchcase(i, c) for c in cited))
    assert not uncited, f"rows that docs/faults.md does not cite: {uncited}"
