"""The fitting pipeline's steps as typed results: each step alone gives what the pipeline puts in the document."""

import dataclasses

import pytest

from driftlab.errors import ValidationError
from driftlab.models.document import ModelDocument
from driftlab.models.fitting import (
    FitOptions,
    FitResult,
    Timer,
    allocate_models,
    build_fit_samples,
    channel_metadata,
    fit_bundles,
    joint_adjust,
    prepare_campaigns,
    screen,
)
from tests.models.test_fitting import synthetic_bundle

OPTIONS = FitOptions(network=False, virtual_sensors=False)


@pytest.fixture(scope="module")
def bundle():
    return synthetic_bundle(0)


@pytest.fixture(scope="module")
def fitted(bundle) -> FitResult:
    return fit_bundles([bundle], OPTIONS)


def test_steps_are_frozen_and_chain_to_the_pipelines_models(bundle, fitted):
    campaigns = prepare_campaigns([bundle], OPTIONS)
    meta = channel_metadata(campaigns.bundles)
    screened = screen(campaigns.bundles, meta, OPTIONS.holdout_fraction)
    samples = build_fit_samples(campaigns, meta, screened, OPTIONS)
    allocation = allocate_models(campaigns.bundles, samples, meta, OPTIONS)
    with pytest.raises(dataclasses.FrozenInstanceError):
        campaigns.machine = "other"  # type: ignore[misc]
    assert campaigns.machine == "vmc-test"
    assert meta.room == ["T49", "T50"]
    assert screened.kept == fitted.document.kept_channels
    assert set(samples.channels) >= set(screened.kept)
    # the staged models before the joint adjustment: every term they chose is in the pipeline's document
    # (which adds the physical terms and, on T1, the lines' corrections)
    in_doc = {(t.element, t.param): {f.name for f in t.features} for t in fitted.document.terms}
    staged = {k: {f.name for f in m.features if f.kind != "session"} for k, m in allocation.models.items()}
    assert any(staged.values())
    for key, names in staged.items():
        assert names <= in_doc.get(key, set()), key


def test_joint_adjust_wrapper_fills_the_result_dict_like_before(bundle):
    campaigns = prepare_campaigns([bundle], OPTIONS)
    meta = channel_metadata(campaigns.bundles)
    screened = screen(campaigns.bundles, meta, OPTIONS.holdout_fraction)
    samples = build_fit_samples(campaigns, meta, screened, OPTIONS)
    allocation = allocate_models(campaigns.bundles, samples, meta, OPTIONS)
    out: dict = {}
    summary = joint_adjust(samples.sample, allocation.models, allocation.dims, result=out)
    assert summary["coefficients"] == len(out["joint"].columns)
    assert summary["weighted_rms_after"] <= summary["weighted_rms_before"]
    assert set(out) == {"campaign_offsets", "joint", "pinning"}


def test_summary_and_to_document(fitted):
    assert isinstance(fitted.to_document(), ModelDocument)
    assert fitted.to_document() is fitted.document
    text = fitted.summary()
    lines = text.splitlines()
    assert lines[0].startswith("machine vmc-test:")
    # one row per validated (axis, term), with its held-out RMSE in um or urad
    rows = [ln for ln in lines if ln.split()[:1] in (["X"], ["Z"])]
    assert len(rows) == len(fitted.validation)
    z_dz = fitted.validation.query("axis == 'Z' and term == 'dz'").iloc[0]
    row = next(ln for ln in rows if ln.split()[:2] == ["Z", "dz"])
    assert f"{z_dz['rmse_holdout'] * 1e3:.2f}" in row.split()
    assert "table 6.3" in text


def test_timer_records_each_lap_and_reports_it():
    seen: list[str] = []
    timer = Timer(seen.append)
    timer.lap("a")
    timer.lap("b")
    assert list(timer.timings) == ["a", "b"] and seen == ["a", "b"]
    assert all(v >= 0 for v in timer.timings.values())


def test_pipeline_times_every_step_in_order(fitted):
    assert list(fitted.timings_s) == [
        "screening",
        "samples",
        "allocation_and_regression",
        "joint_adjustment",
        "lines",
        "validation",
        "virtual_sensors",
        "document",
    ]


def test_campaigns_of_two_machines_are_refused_before_any_step(bundle):
    other = dataclasses.replace(
        bundle, meta=bundle.meta.model_copy(update={"machine": bundle.meta.machine.model_copy(update={"id": "m2"})})
    )
    with pytest.raises(ValidationError, match="different machines"):
        prepare_campaigns([bundle, other], OPTIONS)
    with pytest.raises(ValidationError, match="no campaigns"):
        prepare_campaigns([], OPTIONS)
