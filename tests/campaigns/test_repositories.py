"""The store's repositories on SQLite and PostgreSQL: one engine and schema gate, no alias beside them, keyset
pages, registry listings, job filters and the on-line state's update record."""

from __future__ import annotations

import dataclasses
from datetime import UTC, datetime
from pathlib import Path

import pytest

from driftlab.campaigns import db
from driftlab.campaigns.bundle import load_bundle
from driftlab.campaigns.job_repo import JobFilter
from driftlab.campaigns.online_repo import OnlineStateInfo, OnlineUpdate, StaleOnlineState
from driftlab.campaigns.readings_repo import DriftQuery, ErrorFilter, HistoryPage
from driftlab.campaigns.repository import Page
from driftlab.campaigns.store import Store, connect
from driftlab.errors import BadRequestError, NotFoundError, ValidationError

MACHINE = "vmc-test-01"


@pytest.fixture
def store(store_url: str):
    s = connect(store_url)
    yield s
    s.close()


def test_the_repositories_share_one_engine_and_one_schema_gate(tmp_path: Path) -> None:
    store = connect(f"sqlite:///{tmp_path / 'fresh.sqlite'}")
    try:
        repos = [store.campaigns, store.readings, store.models, store.jobs, store.online]
        assert all(r.engine is store.engine and r.gate is store.gate for r in repos)
        assert store.revision() is None  # nothing made before the first use
        assert store.models.current(MACHINE) is None  # any repository's first read brings the schema to head
        assert store.revision() == db.head_revision() and store.gate.ready
    finally:
        store.close()


#: the names ``Store`` bound beside its repositories before issue 36
OLD_NAMES = (
    "import_bundle import_directory load_campaign campaign_machine list_campaigns delete_campaign refresh_rollups "
    "save_progress progress drift temperature_history condition_history register_model current_model machine_ids "
    "refit_candidates record_job link_queue_job start_job finish_job fail_job delete_job jobs_in_state "
    "last_job_result get_job online_state model_versions save_online_state"
).split()


def test_the_store_has_one_api_its_repositories(store: Store) -> None:
    """No legacy alias beside the repositories: every old name is gone from Store (instance and class)."""
    left = [name for name in OLD_NAMES if hasattr(store, name) or hasattr(Store, name)]
    assert left == []
    public = sorted(n for n in vars(store) if not n.startswith("_"))
    assert public == ["campaigns", "engine", "gate", "jobs", "models", "online", "readings"]


def test_keyset_pages_of_a_history_add_up_to_the_whole(store: Store, bundle_factory) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_factory(scans=25)))
    everything = store.readings.temperature_page(cid, "T1", HistoryPage(limit=10_000))
    assert len(everything) == 25
    pages, after = [], None
    while True:
        page = store.readings.temperature_page(cid, "T1", HistoryPage(after=after, limit=7))
        if not page:
            break
        pages += page
        after = page[-1][0]
    assert pages == everything
    # the time range and the offset narrow the same rows
    t = [row[0] for row in everything]
    window = store.readings.temperature_page(cid, "T1", HistoryPage(start_s=t[3], end_s=t[9], offset=2, limit=3))
    assert window == everything[5:8]
    with pytest.raises(NotFoundError, match="no channel"):
        store.readings.temperature_page(cid, "T99", HistoryPage())


def test_error_pages_filter_and_continue_after_a_seq(store: Store, bundle_factory) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_factory()))
    dz_up = store.readings.error_page(cid, ErrorFilter("Z", "dz", 1), HistoryPage(limit=10_000))
    assert dz_up and all(r.term == "dz" and r.direction == 1 for r in dz_up)
    seqs = [r.seq for r in dz_up]
    assert seqs == sorted(seqs)
    rest = store.readings.error_page(cid, ErrorFilter("Z", "dz", 1), HistoryPage(after=seqs[2], limit=10_000))
    assert [r.seq for r in rest] == seqs[3:]
    with pytest.raises(NotFoundError, match="no campaign"):
        store.readings.error_page(cid + 100, ErrorFilter(), HistoryPage())


def test_a_drift_query_is_checked_before_it_reads(store: Store, bundle_factory) -> None:
    store.campaigns.import_bundle(load_bundle(bundle_factory()))
    with pytest.raises(ValidationError, match="unknown axis"):
        store.readings.query_drift(DriftQuery(MACHINE, "Q", "dz"))
    with pytest.raises(ValidationError, match="direction"):
        store.readings.query_drift(DriftQuery(MACHINE, "Z", "dz", direction=0))
    with pytest.raises(BadRequestError, match="needs a position"):
        store.readings.query_drift(DriftQuery(MACHINE, "Z", "dz", interpolate=True))
    asked = DriftQuery(MACHINE, "Z", "dz", position=130.0, direction=1)
    assert store.readings.query_drift(asked).equals(
        store.readings.drift(MACHINE, "Z", "dz", position=130.0, direction=1)
    )


def test_registry_listing_pages_and_unknown_machines(store: Store, bundle_factory) -> None:
    store.campaigns.import_bundle(load_bundle(bundle_factory()))
    for k in range(3):
        store.models.register(MACHINE, {"k": k})
    assert [m.version for m in store.models.versions(MACHINE, page=Page(2, 1))] == [2, 3]
    assert [m.status for m in store.models.versions(MACHINE, "current")] == ["current"]
    retired = store.models.retire(MACHINE, 3)
    assert retired.status == "retired" and retired.retired_at is not None
    assert store.models.current(MACHINE) is None
    assert store.models.promote(MACHINE, 1).status == "current"
    assert store.models.versions("no-such-machine") == []  # what the registry's own listing expects
    with pytest.raises(NotFoundError, match="no machine"):
        store.models.versions("no-such-machine", known_machine=True)  # what the API answers with 404
    assert store.campaigns.machine(MACHINE).current_model_version == 1


def test_job_listing_filters_by_state_kind_and_machine(store: Store, bundle_factory) -> None:
    for machine in ("m1", "m2"):
        store.campaigns.import_bundle(load_bundle(bundle_factory(machine=machine)))
    a = store.jobs.record("fit", {}, machine_id="m1")
    b = store.jobs.record("diagnose", {}, machine_id="m2")
    c = store.jobs.record("fit", {}, machine_id="m2")
    store.jobs.start(c, "w")
    assert [j.id for j in store.jobs.find()] == [c, b, a]  # newest first
    assert [j.id for j in store.jobs.find(JobFilter(kind="fit"))] == [c, a]
    assert [j.id for j in store.jobs.find(JobFilter(machine_id="m2", state="queued"))] == [b]
    assert [j.id for j in store.jobs.find(JobFilter(kinds=("diagnose",)))] == [b]
    assert [j.id for j in store.jobs.find(page=Page(1, 1))] == [b]


def test_an_online_update_is_stored_and_read_back_as_its_state(store: Store, bundle_factory) -> None:
    store.campaigns.import_bundle(load_bundle(bundle_factory()))
    update = OnlineUpdate(None, 1, 0.98, 3, {"dx": [1.0]}, {"dx": [[2.0]]})
    probe = {"measured_at": datetime(2026, 3, 3, tzinfo=UTC), "x": 0, "y": 0, "z": 0, "dx": 1.0, "dy": 0, "dz": 0}
    state, ids = store.online.save(MACHINE, None, update, [probe])
    assert isinstance(state, OnlineStateInfo) and len(ids) == 1
    assert (state.machine_id, state.version, state.lam, state.n_updates) == (MACHINE, 1, 0.98, 3)
    assert store.online.get(MACHINE) == state
    with pytest.raises(StaleOnlineState):  # computed from no state, but there is one now
        store.online.save(MACHINE, None, update)
    moved, _ = store.online.save(MACHINE, 1, dataclasses.replace(update, n_updates=4))
    assert moved.version == 2 and moved.n_updates == 4
    assert store.table_counts()["probe_measurements"] == 1
