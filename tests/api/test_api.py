"""The API through HTTP (ASGI transport) on SQLite and PostgreSQL, seeded by a bundle import and a model."""

from __future__ import annotations

import asyncio
import json
import math

import httpx
import pytest

from driftlab.models.online import ONLINE_P0
from tests.api.helpers import AUTH, MACHINE, TOKEN, Seeded, model_document

pytestmark = pytest.mark.anyio

PROBLEM = "application/problem+json"


def assert_problem(r: httpx.Response, status: int) -> dict:
    """Check a problem+json answer of this status and return its body."""
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["status"] == status and body["type"].startswith("urn:driftlab:problem:")
    assert body["title"] and body["detail"] and "Traceback" not in body["detail"]
    assert body["instance"] == r.request.url.path
    return body


async def test_machines_and_campaigns(client: httpx.AsyncClient, seeded: Seeded) -> None:
    r = await client.get("/machines")
    assert r.status_code == 200
    (m,) = r.json()["items"]
    assert m["id"] == MACHINE and m["campaigns"] == 1 and m["current_model_version"] == seeded.model_version
    assert (await client.get(f"/machines/{MACHINE}")).json() == m
    assert_problem(await client.get("/machines/nope"), 404)

    r = await client.get("/campaigns", params={"machine_id": MACHINE})
    (c,) = r.json()["items"]
    assert c["id"] == seeded.campaign_id and c["channels"] == 4 and c["scans"] == 80 and c["stages"] == 2
    assert c["error_samples"] == 8 * 2 * 5 * 3
    assert (await client.get("/campaigns", params={"machine_id": "other"})).json()["items"] == []
    d = (await client.get(f"/campaigns/{seeded.campaign_id}")).json()
    assert [s["name"] for s in d["stage_list"]] == ["spindle-8k", "cool"]
    assert [ch["name"] for ch in d["channel_list"]] == ["T1", "T2", "T49", "T50"]
    assert d["meta"]["machine"]["id"] == MACHINE
    stages = (await client.get(f"/campaigns/{seeded.campaign_id}/stages")).json()
    assert stages == d["stage_list"]
    assert [ch["is_room"] for ch in (await client.get(f"/campaigns/{seeded.campaign_id}/channels")).json()] == [
        False,
        False,
        True,
        True,
    ]
    assert_problem(await client.get("/campaigns/999"), 404)
    assert_problem(await client.get("/campaigns/abc"), 400)


async def test_temperature_history_paging_cursor_and_buckets(client: httpx.AsyncClient, seeded: Seeded) -> None:
    base = f"/campaigns/{seeded.campaign_id}/temperatures"
    full = (await client.get(f"{base}/T2", params={"limit": 10000})).json()
    assert len(full["points"]) == 80 and full["next_cursor"] is None
    assert full["points"][3]["value"] is None  # the missing reading is null, not NaN
    assert [p["time_s"] for p in full["points"]] == [30.0 * k for k in range(80)]
    # cursor paging walks the same rows without gaps or repeats
    seen, cursor = [], None
    while True:
        params = {"limit": 25, **({"cursor": cursor} if cursor else {})}
        page = (await client.get(f"{base}/T2", params=params)).json()
        seen += page["points"]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == full["points"]
    # offset paging and a time range
    page = (await client.get(f"{base}/T2", params={"limit": 5, "offset": 10})).json()
    assert page["points"] == full["points"][10:15]
    ranged = (await client.get(f"{base}/T2", params={"start_s": 300, "end_s": 600})).json()["points"]
    assert [p["time_s"] for p in ranged] == [300.0 + 30 * k for k in range(11)]
    # buckets: min/mean/max from SQL, all readings counted
    b = (await client.get(f"{base}/T1", params={"buckets": 8})).json()
    assert "points" not in b and len(b["buckets"]) == 8 and sum(x["n"] for x in b["buckets"]) == 80
    values = [p["value"] for p in (await client.get(f"{base}/T1", params={"limit": 10})).json()["points"]]
    first = b["buckets"][0]
    assert first["n"] == 10 and math.isclose(first["mean"], sum(values) / 10, rel_tol=1e-12)
    assert first["min"] == min(values) and first["max"] == max(values)
    assert_problem(await client.get(f"{base}/T99"), 404)
    assert_problem(await client.get(f"{base}/T1", params={"cursor": "garbage"}), 400)
    assert_problem(await client.get(f"{base}/T1", params={"start_s": 10, "end_s": 5}), 400)
    assert_problem(await client.get(f"{base}/T1", params={"limit": 0}), 400)


async def test_condition_and_error_histories(client: httpx.AsyncClient, seeded: Seeded) -> None:
    base = f"/campaigns/{seeded.campaign_id}"
    r = (
        await client.get(f"{base}/conditions", params=[("column", "spindle_rpm"), ("column", "z"), ("limit", 3)])
    ).json()
    assert r["columns"] == ["spindle_rpm", "z"]
    assert r["points"][0] == {"time_s": 0.0, "spindle_rpm": 8000.0, "z": None}
    assert r["next_cursor"]
    nxt = (await client.get(f"{base}/conditions", params={"cursor": r["next_cursor"], "limit": 3})).json()
    assert nxt["points"][0]["time_s"] == 90.0
    b = (await client.get(f"{base}/conditions", params={"column": "spindle_rpm", "buckets": 2})).json()
    assert [x["values"]["spindle_rpm"]["mean"] for x in b["buckets"]] == [8000.0, 0.0]
    assert_problem(await client.get(f"{base}/conditions", params={"column": "torque"}), 400)

    e = (await client.get(f"{base}/errors", params={"term": "dz", "direction": -1, "limit": 1000})).json()
    assert len(e["items"]) == 8 * 5 and {i["term"] for i in e["items"]} == {"dz"}
    assert all(i["direction"] == -1 for i in e["items"])
    seqs, cursor = [], None
    while True:
        params = {"limit": 50, **({"cursor": cursor} if cursor else {})}
        page = (await client.get(f"{base}/errors", params=params)).json()
        seqs += [i["seq"] for i in page["items"]]
        cursor = page["next_cursor"]
        if not cursor:
            break
    assert seqs == sorted(seqs) and len(seqs) == len(set(seqs)) == 240
    assert_problem(await client.get(f"{base}/errors", params={"axis": "Q"}), 400)


async def test_latest_scan_of_the_machine(client: httpx.AsyncClient, seeded: Seeded) -> None:
    from tests.api.helpers import small_frames

    temps, _, _ = small_frames()
    r = (await client.get(f"/machines/{MACHINE}/temperatures/latest")).json()
    assert r["campaign_id"] == seeded.campaign_id and r["time_s"] == temps["time_s"].iloc[-1]
    assert r["time"] == "2026-03-02T08:39:30Z"
    assert r["temperatures"] == {c: temps[c].iloc[-1] for c in ("T1", "T2", "T49", "T50")}
    assert_problem(await client.get("/machines/ghost/temperatures/latest"), 404)


async def test_drift(client: httpx.AsyncClient, seeded: Seeded) -> None:
    r = (
        await client.get(
            f"/machines/{MACHINE}/drift", params={"axis": "Z", "term": "dz", "position": 410, "direction": 1}
        )
    ).json()
    assert len(r["points"]) == 8 and all(p["position"] == 400.0 for p in r["points"])
    assert r["points"][0]["time"].startswith("2026-03-02T08:00")
    values = [p["value"] for p in r["points"]]
    assert values == sorted(values)  # the planted drift grows sweep after sweep
    i = (
        await client.get(
            f"/machines/{MACHINE}/drift",
            params={"axis": "Z", "term": "dz", "position": 150, "interpolate": True, "direction": 1},
        )
    ).json()
    assert len(i["points"]) == 8 and all(p["position"] == 150.0 for p in i["points"])
    assert_problem(
        await client.get(f"/machines/{MACHINE}/drift", params={"axis": "Z", "term": "dz", "interpolate": True}), 400
    )
    assert_problem(await client.get("/machines/ghost/drift", params={"axis": "Z", "term": "dz"}), 404)


async def test_current_model_etag_304_and_cache_invalidation(client: httpx.AsyncClient, seeded: Seeded) -> None:
    url = f"/machines/{MACHINE}/model/current"
    r = await client.get(url)
    assert r.status_code == 200 and r.headers["etag"].startswith('"')
    body = r.json()
    assert body["version"] == seeded.model_version and body["status"] == "current"
    assert body["document"]["machine"] == MACHINE and body["document"]["version"] == seeded.model_version
    etag = r.headers["etag"]
    r304 = await client.get(url, headers={"If-None-Match": etag})
    assert r304.status_code == 304 and r304.content == b"" and r304.headers["etag"] == etag
    assert (await client.get(url, headers={"If-None-Match": '"other"'})).status_code == 200
    assert (await client.get(url, headers={"If-None-Match": f'"x", W/{etag}'})).status_code == 304
    cache = client.app.state.driftlab.models  # type: ignore[attr-defined]
    loads = cache.loads
    for _ in range(20):
        again = await client.get(url)
        # the cache-hit fast path answers exactly like the route did
        assert again.content == r.content and again.headers == r.headers
    assert cache.loads == loads  # the hot path is served from the cache
    cache.invalidate()
    routed = await client.get(url, headers={"If-None-Match": etag})
    fast = await client.get(url, headers={"If-None-Match": etag})
    assert routed.status_code == fast.status_code == 304 and routed.headers == fast.headers
    assert cache.loads == loads + 1

    # a new version changes the ETag at once (invalidation, not TTL)
    new = await client.post(
        f"/machines/{MACHINE}/models", json={"document": model_document(coefficient=0.003)}, headers=AUTH
    )
    assert new.status_code == 201 and new.json()["version"] == seeded.model_version + 1
    assert new.headers["location"].endswith(f"/models/{seeded.model_version + 1}")
    r2 = await client.get(url, headers={"If-None-Match": etag})
    assert r2.status_code == 200 and r2.headers["etag"] != etag and r2.json()["version"] == seeded.model_version + 1
    # promote the old version back: the ETag returns to the first one
    p = await client.post(f"/machines/{MACHINE}/models/{seeded.model_version}/promote", headers=AUTH)
    assert p.status_code == 200 and p.json()["status"] == "current"
    r3 = await client.get(url, headers={"If-None-Match": etag})
    assert r3.status_code == 304
    versions = (await client.get(f"/machines/{MACHINE}/models")).json()["items"]
    assert [(v["version"], v["status"]) for v in versions] == [(1, "current"), (2, "retired")]
    # retire the current one: no current model, 404 problem
    assert (await client.post(f"/machines/{MACHINE}/models/1/retire", headers=AUTH)).status_code == 200
    assert_problem(await client.get(url), 404)
    assert_problem(await client.post(f"/machines/{MACHINE}/models/1/retire", headers=AUTH), 409)
    assert_problem(await client.post(f"/machines/{MACHINE}/models/9/promote", headers=AUTH), 404)
    one = await client.get(f"/machines/{MACHINE}/models/2")
    assert one.status_code == 200 and one.json()["document"]["terms"][0]["coefficients"] == [0.001, 0.003]
    assert one.headers["etag"] != etag
    listing = (await client.get("/models", params={"status": "retired"})).json()["items"]
    assert {v["version"] for v in listing} == {1, 2} and all("document" not in v for v in listing)


async def test_model_registration_is_validated(client: httpx.AsyncClient, store) -> None:
    before = store.table_counts()
    bad = model_document()
    bad["terms"][0]["coefficients"] = [1.0]
    assert_problem(await client.post(f"/machines/{MACHINE}/models", json={"document": bad}, headers=AUTH), 422)
    other = model_document(machine="someone-else")
    assert_problem(await client.post(f"/machines/{MACHINE}/models", json={"document": other}, headers=AUTH), 422)
    assert_problem(await client.post("/machines/someone-else/models", json={"document": other}, headers=AUTH), 404)
    assert_problem(await client.post(f"/machines/{MACHINE}/models", json={"doc": 1}, headers=AUTH), 422)
    nan = model_document()
    raw = json.dumps({"document": nan}).replace("0.002", "NaN")  # Python's parser would take it
    body = assert_problem(
        await client.post(
            f"/machines/{MACHINE}/models", content=raw, headers={**AUTH, "Content-Type": "application/json"}
        ),
        422,
    )
    assert "NaN is not a JSON number" in body["detail"]  # refused as it is parsed (api.strict)
    nul = model_document()
    nul["screening"] = {"note": "a\x00b"}
    body = assert_problem(await client.post(f"/machines/{MACHINE}/models", json={"document": nul}, headers=AUTH), 422)
    assert "NUL" in body["detail"]
    assert store.table_counts() == before


def _unsafe(kind: str) -> dict:
    """Return a document whose envelope or ranges would switch a guard off (issue 34)."""
    d = model_document()
    if kind == "max_correction":
        d["envelope"] = {"max_correction": {"Z": 1e9}}
    elif kind == "margin":
        d["envelope"] = {"extrapolation_margin_degC": 1e9}
    elif kind == "rotary":
        d["envelope"] = {"max_correction": {"A": 45.0}}
    elif kind == "no-terms":
        d["terms"] = []
    elif kind == "min-above-max":
        d["inputs"]["T1"] = {"reference": 20.0, "min": 30.0, "max": 19.0}
    return d


@pytest.mark.parametrize(
    "kind,needle",
    [
        ("max_correction", "max_correction of Z 1e+09 mm is above 5 mm"),
        ("margin", "extrapolation_margin_degC"),
        ("rotary", "max_correction of A 45 deg is above 1 deg"),
        ("no-terms", "has no terms"),
        ("min-above-max", "min 30 is above max 19"),
    ],
)
async def test_documents_that_would_switch_a_guard_off_are_refused(
    client: httpx.AsyncClient, store, kind: str, needle: str
) -> None:
    before = store.table_counts()
    reply = await client.post(f"/machines/{MACHINE}/models", json={"document": _unsafe(kind)}, headers=AUTH)
    body = assert_problem(reply, 422)
    assert needle in body["detail"]
    assert store.table_counts() == before


@pytest.mark.parametrize(
    "headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"}, {"Authorization": TOKEN}]
)
async def test_writes_need_the_token_and_change_nothing(
    client: httpx.AsyncClient, store, seeded: Seeded, headers: dict
) -> None:
    before = store.table_counts()
    writes = [
        ("POST", f"/machines/{MACHINE}/models", {"document": model_document()}),
        ("POST", f"/machines/{MACHINE}/models/1/promote", None),
        ("POST", f"/machines/{MACHINE}/models/1/retire", None),
        ("POST", "/jobs", {"kind": "diagnose", "campaign_ids": [seeded.campaign_id]}),
        (
            "POST",
            f"/machines/{MACHINE}/online/probe",
            {"x": 0, "y": 0, "z": 0, "dx": 0, "dy": 0, "dz": 0, "temperatures": {"T1": 21, "T2": 22}},
        ),
        ("DELETE", f"/campaigns/{seeded.campaign_id}", None),
        ("DELETE", f"/machines/{MACHINE}/online", None),
    ]
    for method, url, body in writes:
        r = await client.request(method, url, json=body, headers=headers)
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
    assert store.table_counts() == before
    assert (await client.get(f"/machines/{MACHINE}/model/current")).json()["version"] == 1


async def test_writes_are_refused_when_no_token_is_configured(seeded: Seeded, store) -> None:
    from driftlab.api.app import create_app

    app = create_app(seeded.url, token="", run_jobs=False)
    before = store.table_counts()
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
        for headers in ({}, {"Authorization": "Bearer "}, AUTH):
            r = await c.post(f"/machines/{MACHINE}/models/1/retire", headers=headers)
            assert_problem(r, 403)
        assert (await c.get(f"/machines/{MACHINE}/model/current")).status_code == 200
    assert store.table_counts() == before


async def _wait_job(client: httpx.AsyncClient, job_id: int) -> dict:
    """Poll a job until it is done or failed (bounded by polls, not by wall clock)."""
    for _ in range(600):
        job = (await client.get(f"/jobs/{job_id}")).json()
        if job["state"] in ("done", "failed"):
            return job
        await asyncio.sleep(0.1)
    raise AssertionError(f"job {job_id} still {job['state']}")


async def test_fit_and_diagnosis_jobs_run_in_the_background(client: httpx.AsyncClient, seeded: Seeded) -> None:
    etag = (await client.get(f"/machines/{MACHINE}/model/current")).headers["etag"]
    r = await client.post("/jobs", json={"kind": "fit", "machine_id": MACHINE}, headers=AUTH)
    assert r.status_code == 202 and r.json()["state"] in ("queued", "running")
    assert r.headers["location"] == f"/jobs/{r.json()['id']}"
    assert r.json()["params"]["campaigns"] == [seeded.campaign_id]
    job = await _wait_job(client, r.json()["id"])
    assert job["state"] == "done", job["error"]
    assert job["result"]["model_version"] == seeded.model_version + 1
    cur = await client.get(f"/machines/{MACHINE}/model/current", headers={"If-None-Match": etag})
    assert cur.status_code == 200 and cur.json()["version"] == seeded.model_version + 1
    assert cur.json()["source_campaigns"] == [seeded.campaign_id]

    d = await client.post("/jobs", json={"kind": "diagnose", "campaign_ids": [seeded.campaign_id]}, headers=AUTH)
    job = await _wait_job(client, d.json()["id"])
    assert job["state"] == "done", job["error"]
    assert job["result"]["report"]["format"].startswith("driftlab-diagnosis")
    assert job["machine_id"] == MACHINE and job["campaign_id"] == seeded.campaign_id
    listed = (await client.get("/jobs", params={"state": "done"})).json()["items"]
    assert [j["kind"] for j in listed] == ["diagnose", "fit"]
    assert_problem(await client.post("/jobs", json={"kind": "diagnose", "campaign_ids": []}, headers=AUTH), 422)
    assert_problem(await client.post("/jobs", json={"kind": "fit", "campaign_ids": [999]}, headers=AUTH), 404)
    assert_problem(await client.post("/jobs", json={"kind": "sing"}, headers=AUTH), 422)
    assert_problem(await client.get("/jobs/99999"), 404)


async def test_online_probe_updates_persist_and_converge(client: httpx.AsyncClient, seeded: Seeded, store) -> None:
    url = f"/machines/{MACHINE}/online/probe"
    assert_problem(await client.get(f"/machines/{MACHINE}/online"), 404)
    # off-line prediction at T1=25, T2=23 (no lags): T1.dz = 0.001 + 0.002*5, phi_z.dx = 0.0005*2
    offset = {"dx": 0.004, "dy": -0.002, "dz": 0.003}  # what the off-line model misses
    last = None
    for k in range(30):
        t1 = 25.0 + 0.1 * (k % 5)
        body = {
            "x": 100.0,
            "y": 50.0,
            "z": -200.0,
            "a_deg": 0.0,
            "b_deg": 0.0,
            "temperatures": {"T1": t1, "T2": 23.0, "T49": 20.5},
            "measured_at": f"2026-03-03T08:{k:02d}:00Z",
        }
        if k == 0:
            body |= {"forgetting": 0.95}
        # measure exactly what the models predict plus the constant offset
        off = client.app.state.driftlab  # type: ignore[attr-defined]
        import numpy as np

        from driftlab.models.document import predict_workspace_errors

        row = off.models.get(MACHINE).row
        w = predict_workspace_errors(row.document, body["temperatures"], np.array([[100.0, 50.0, -200.0, 0, 0]]))[0]
        body |= {"dx": float(w[3]) + offset["dx"], "dy": float(w[4]) + offset["dy"], "dz": float(w[5]) + offset["dz"]}
        r = await client.post(url, json=body, headers=AUTH)
        assert r.status_code == 200, r.text
        last = r.json()
        assert last["n_updates"] == k + 1 and last["forgetting"] == 0.95
    assert last is not None
    # intercept-only RLS from P(0) = p0 on a constant residual r: theta_n = r S / (lambda^n / p0 + S),
    # S = sum lambda^i (theta0 = 0 weighs 1 / p0 of one probe, forgotten like the probes)
    lam, n = 0.95, 30
    s = sum(lam**i for i in range(n))
    for c in ("dx", "dy", "dz"):
        assert math.isclose(last["online_prediction"][c], offset[c] * s / (lam**n / ONLINE_P0 + s), rel_tol=1e-9)
        assert abs(last["prior_error"][c]) < 0.02 * abs(offset[c])
        assert math.isclose(last["correction"][c], -(last["offline_prediction"][c] + last["online_prediction"][c]))
    state = (await client.get(f"/machines/{MACHINE}/online")).json()
    assert state["n_updates"] == 30 and state["theta"] == last["theta"]
    # the state is the one `driftlab online` continues from
    from driftlab.jobs.online import latest_online_states

    shared = latest_online_states(store, MACHINE, seeded.model_version)
    assert shared["dz"].n_updates == 30 and shared["dz"].theta.tolist() == last["theta"]["dz"]
    counts = store.table_counts()
    assert counts["probe_measurements"] == 30
    # the same probing twice is refused and changes nothing; a channel change is refused
    dup = await client.post(url, json={**body}, headers=AUTH)
    assert_problem(dup, 409)
    assert_problem(
        await client.post(url, json={**body, "measured_at": "2026-03-04T00:00:00Z", "forgetting": 0.9}, headers=AUTH),
        409,
    )
    assert_problem(
        await client.post(
            url, json={**body, "measured_at": "2026-03-04T00:00:00Z", "temperatures": {"T1": 25.0}}, headers=AUTH
        ),
        422,
    )
    assert store.table_counts() == counts
    # a reset (after maintenance) starts the next probe from the off-line model; the probe history stays
    assert (await client.delete(f"/machines/{MACHINE}/online", headers=AUTH)).status_code == 204
    assert_problem(await client.get(f"/machines/{MACHINE}/online"), 404)
    assert_problem(await client.delete(f"/machines/{MACHINE}/online", headers=AUTH), 404)
    assert store.table_counts()["probe_measurements"] == 30
    fresh = await client.post(
        url, json={**body, "measured_at": "2026-03-05T00:00:00Z", "forgetting": 0.9}, headers=AUTH
    )
    assert fresh.status_code == 200 and fresh.json()["n_updates"] == 1 and fresh.json()["forgetting"] == 0.9
    # from P(0) = p0: theta_1 = r p0 / (lambda + p0) of the first residual alone
    for c in ("dx", "dy", "dz"):
        want = offset[c] * ONLINE_P0 / (0.9 + ONLINE_P0)
        assert math.isclose(fresh.json()["online_prediction"][c], want, rel_tol=1e-6)
    # a new current model starts a new on-line state
    await client.post(f"/machines/{MACHINE}/models", json={"document": model_document()}, headers=AUTH)
    assert_problem(await client.get(f"/machines/{MACHINE}/online"), 404)


async def test_unknown_route_and_method_are_problems(client: httpx.AsyncClient) -> None:
    assert_problem(await client.get("/nowhere"), 404)
    assert_problem(await client.put("/machines", headers=AUTH), 405)


async def test_unexpected_errors_are_500_problems_with_the_traceback_logged(seeded: Seeded, caplog) -> None:
    from driftlab.api.app import create_app

    app = create_app(seeded.url, TOKEN, run_jobs=False)

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("secret internals")

    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
        r = await c.get("/boom")
    body = assert_problem(r, 500)
    assert "secret" not in body["detail"]
    assert any("secret internals" in (rec.exc_text or "") or rec.exc_info for rec in caplog.records)


async def test_openapi_declares_every_operation_and_problem(client: httpx.AsyncClient) -> None:
    schema = (await client.get("/openapi.json")).json()
    ops = {(m.upper(), p) for p, item in schema["paths"].items() for m in item}
    assert ("GET", "/machines/{machine_id}/model/current") in ops and len(ops) >= 20
    for path, item in schema["paths"].items():
        for method, op in item.items():
            for status in ("404", "422", "500"):
                assert PROBLEM in op["responses"][status]["content"], (method, path, status)
            if method in ("post", "delete"):
                assert PROBLEM in op["responses"]["401"]["content"]
                # the bearer scheme: /docs has an Authorize button and each write says it needs the token
                assert op["security"] == [{"bearer": []}], (method, path)
            else:
                assert "security" not in op, (method, path)
    assert schema["components"]["securitySchemes"]["bearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": "the API token (DRIFTLAB_API_TOKEN); reads need none, every write needs it",
    }
    assert (await client.get("/health")).json()["status"] == "ok"


async def test_changes_by_other_processes_are_seen_after_the_ttl(seeded: Seeded, store) -> None:
    from driftlab.api.app import create_app
    from driftlab.jobs import registry as model_registry

    app = create_app(seeded.url, TOKEN, run_jobs=False, model_cache_ttl_s=0.05)
    url = f"/machines/{MACHINE}/model/current"
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
        first = await c.get(url)
        assert first.json()["version"] == 1
        model_registry.register_model(store, model_document(coefficient=0.005), [seeded.campaign_id])  # not via the API
        versions = []
        for _ in range(200):  # bounded polls; the background refresh lands within a few
            await asyncio.sleep(0.02)
            r = await c.get(url, headers={"If-None-Match": first.headers["etag"]})
            versions.append(r.status_code)
            if r.status_code == 200:
                assert r.json()["version"] == 2 and r.headers["etag"] != first.headers["etag"]
                break
        else:
            raise AssertionError(f"the new version was never served: {versions[-5:]}")
