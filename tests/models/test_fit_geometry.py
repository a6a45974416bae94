"""The fit's HTM chain uses the link lengths a machine states (machine.geometry), not the virtual machine's."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from effects_generator import make_case  # noqa: E402

from driftlab.campaigns.bundle import Bundle, _as_meta  # noqa: E402
from driftlab.errors import ValidationError  # noqa: E402
from driftlab.models.fitting import FitOptions, chain_dims, fit_bundles  # noqa: E402
from driftlab.physics.kinematics import TABLE_A1  # noqa: E402


def _with_links(bundle: Bundle, column_mm: tuple[float, float, float]) -> Bundle:
    meta = bundle.meta.model_dump(exclude_none=True)
    meta["machine"]["geometry"] = {"links_mm": {"column": list(column_mm), "spindle_head": [0.0, -250.0, -150.0]}}
    return Bundle(
        name=bundle.name,
        meta=_as_meta(meta),
        temperatures=bundle.temperatures,
        conditions=bundle.conditions,
        errors=bundle.errors,
    )


def test_stated_links_replace_table_a1_in_the_chain_and_the_document() -> None:
    case = make_case([], seed=1, hours=24.0, terms={"X": ["dz"]}, n_channels=8)
    bundle = _with_links(case.bundle, (0.0, 300.0, 900.0))
    dims = chain_dims([bundle])
    assert dims["T2"] == (0.0, 300.0, 900.0) and dims["T1"] == (0.0, -250.0, -150.0)
    assert dims["T3"] == tuple(TABLE_A1["T3"])  # not stated: Table A.1's
    doc = fit_bundles([bundle], FitOptions(network=False)).document
    assert doc.dims["T2"] == [0.0, 300.0, 900.0]
    # without a stated geometry the chain is Table A.1's
    assert chain_dims([case.bundle]) == {k: tuple(v) for k, v in TABLE_A1.items()}


def test_campaigns_stating_different_links_are_refused() -> None:
    a = _with_links(make_case([], seed=1, hours=12.0).bundle, (0.0, 300.0, 900.0))
    b = _with_links(make_case([], seed=2, hours=12.0).bundle, (0.0, 300.0, 950.0))
    with pytest.raises(ValidationError, match="different link lengths"):
        chain_dims([a, b])
