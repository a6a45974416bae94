"""A corpus of hostile and malformed requests (issue 13), on SQLite and PostgreSQL.

Each case asserts the status, that the answer is an RFC 9457 problem document naming the problem,
and that the store is unchanged (row counts of every table). Then: a write's body is never read
before its token is checked, bodies over the limit are 413 whether announced or streamed, every
machine id that import accepts is addressable, and concurrent imports and deletes are correct.
"""

from __future__ import annotations

import asyncio
import base64
import json
import threading
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest

from driftlab.api.app import create_app
from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.campaigns.store import Store, connect
from driftlab.errors import ConflictError
from tests.api.helpers import AUTH, MACHINE, TOKEN, Seeded, seed, small_frames, small_meta

pytestmark = pytest.mark.anyio

LIMIT = 64 << 10  # the body limit of these tests' app (the default is 8 MiB)
JSON = {"content-type": "application/json"}
BAD_JSON = b'{"kind": "fit", '


def _cursor(doc: Any) -> str:
    return base64.urlsafe_b64encode(json.dumps(doc).encode()).decode().rstrip("=")


def _deep(n: int) -> bytes:
    return b"[" * n + b"]" * n


#: (id, method, path template ({cid}, {m}), keyword arguments of httpx, status, text in the detail)
CASES: list[tuple[str, str, str, dict[str, Any], int, str]] = [
    # writes without a valid token: 401/403 before the body is looked at
    ("jobs-bad-json-no-token", "POST", "/jobs", {"content": BAD_JSON, "headers": JSON}, 401, "missing bearer token"),
    (
        "models-bad-json-no-token",
        "POST",
        "/machines/{m}/models",
        {"content": BAD_JSON, "headers": JSON},
        401,
        "missing bearer token",
    ),
    (
        "probe-bad-json-no-token",
        "POST",
        "/machines/{m}/online/probe",
        {"content": BAD_JSON, "headers": JSON},
        401,
        "missing bearer token",
    ),
    ("promote-no-token", "POST", "/machines/{m}/models/1/promote", {}, 401, "missing bearer token"),
    (
        "retire-wrong-token",
        "POST",
        "/machines/{m}/models/1/retire",
        {"headers": {"Authorization": "Bearer nope"}},
        401,
        "invalid bearer token",
    ),
    ("delete-no-token", "DELETE", "/campaigns/{cid}", {}, 401, "missing bearer token"),
    (
        "delete-basic-auth",
        "DELETE",
        "/campaigns/{cid}",
        {"headers": {"Authorization": "Basic dXNlcjpwdw=="}},
        401,
        "invalid bearer token",
    ),
    (
        "jobs-empty-bearer",
        "POST",
        "/jobs",
        {"json": {"kind": "fit"}, "headers": {"Authorization": "Bearer "}},
        401,
        "invalid bearer token",
    ),
    (
        "huge-body-no-token",
        "POST",
        "/jobs",
        {"content": b"x" * (LIMIT * 4), "headers": JSON},
        401,
        "missing bearer token",
    ),
    # bodies over the limit, with the token
    (
        "huge-body-with-token",
        "POST",
        "/jobs",
        {"content": b"x" * (LIMIT * 4), "headers": {**AUTH, **JSON}},
        413,
        "larger than the limit",
    ),
    (
        "huge-model-document",
        "POST",
        "/machines/{m}/models",
        {"json": {"document": {"pad": "p" * LIMIT}}, "headers": AUTH},
        413,
        "larger than the limit",
    ),
    # malformed bodies, with the token: 400/422, nothing stored
    ("jobs-bad-json", "POST", "/jobs", {"content": BAD_JSON, "headers": {**AUTH, **JSON}}, 422, "JSON"),
    (
        "jobs-deep-json",
        "POST",
        "/jobs",
        {"content": _deep(20_000), "headers": {**AUTH, **JSON}},
        400,
        "error parsing the body",
    ),
    (
        "probe-infinite-number",
        "POST",
        "/machines/{m}/online/probe",
        {"content": b'{"x": 1e400, "y": 0, "z": 0}', "headers": {**AUTH, **JSON}},
        422,
        "finite",
    ),
    ("jobs-unknown-kind", "POST", "/jobs", {"json": {"kind": "sing"}, "headers": AUTH}, 422, "kind"),
    (
        "jobs-huge-campaign-id",
        "POST",
        "/jobs",
        {"json": {"kind": "diagnose", "campaign_ids": [10**40]}, "headers": AUTH},
        422,
        "campaign_ids",
    ),
    ("delete-missing-campaign", "DELETE", "/campaigns/999999", {"headers": AUTH}, 404, "no campaign 999999"),
    # cursors: every malformed one is 400, huge integers included
    (
        "cursor-huge-int-temperature",
        "GET",
        "/campaigns/{cid}/temperatures/T1",
        {"params": {"cursor": _cursor({"k": "temperature", "after": 10**100})}},
        400,
        "not a valid temperature cursor",
    ),
    (
        "cursor-100-digits",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": base64.urlsafe_b64encode(b'{"k":"error","after":' + b"9" * 100 + b"}").decode()}},
        400,
        "not a valid error cursor",
    ),
    (
        "cursor-huge-int-error",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": _cursor({"k": "error", "after": 2**63})}},
        400,
        "not a valid error cursor",
    ),
    (
        "cursor-negative-seq",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": _cursor({"k": "error", "after": -1})}},
        400,
        "not a valid error cursor",
    ),
    (
        "cursor-float-seq",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": _cursor({"k": "error", "after": 1.5})}},
        400,
        "not a valid error cursor",
    ),
    (
        "cursor-other-kind",
        "GET",
        "/campaigns/{cid}/conditions",
        {"params": {"cursor": _cursor({"k": "error", "after": 1})}},
        400,
        "not a valid condition cursor",
    ),
    (
        "cursor-not-base64",
        "GET",
        "/campaigns/{cid}/temperatures/T1",
        {"params": {"cursor": "%%%"}},
        400,
        "not a valid temperature cursor",
    ),
    (
        "cursor-deep-json",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": base64.urlsafe_b64encode(_deep(70)).decode()}},
        400,
        "not a valid error cursor",
    ),
    (
        "cursor-nan",
        "GET",
        "/campaigns/{cid}/temperatures/T1",
        {"params": {"cursor": _cursor({"k": "temperature", "after": float("nan")})}},
        400,
        "not a valid",
    ),
    ("cursor-too-long", "GET", "/campaigns/{cid}/errors", {"params": {"cursor": "A" * 500}}, 400, "cursor"),
    (
        "cursor-and-offset",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"cursor": _cursor({"k": "error", "after": 1}), "offset": 3}},
        400,
        "either offset or cursor",
    ),
    # other parameters
    ("limit-huge", "GET", "/campaigns", {"params": {"limit": str(10**30)}}, 400, "limit"),
    ("offset-negative", "GET", "/machines", {"params": {"offset": "-1"}}, 400, "offset"),
    ("campaign-id-huge", "GET", "/campaigns/" + "9" * 40, {}, 400, "campaign_id"),
    ("campaign-id-text", "GET", "/campaigns/abc", {}, 400, "campaign_id"),
    ("version-huge", "GET", "/machines/{m}/models/" + "9" * 30, {}, 400, "version"),
    ("machine-id-bad-chars", "GET", "/machines/bad id!", {}, 400, "machine_id"),
    ("machine-id-too-long", "GET", "/models", {"params": {"machine_id": "m" * 100}}, 400, "machine_id"),
    ("start-s-nan", "GET", "/campaigns/{cid}/temperatures/T1", {"params": {"start_s": "nan"}}, 400, "start_s"),
    ("start-s-1e300", "GET", "/campaigns/{cid}/conditions", {"params": {"start_s": "1e300"}}, 400, "start_s"),
    (
        "time-range-backwards",
        "GET",
        "/campaigns/{cid}/errors",
        {"params": {"start_s": 10, "end_s": 5}},
        400,
        "ends (5.0) before it starts",
    ),
    ("buckets-zero", "GET", "/campaigns/{cid}/temperatures/T1", {"params": {"buckets": 0}}, 400, "buckets"),
    ("axis-unknown", "GET", "/campaigns/{cid}/errors", {"params": {"axis": "Q"}}, 400, "axis"),
    ("direction-zero", "GET", "/campaigns/{cid}/errors", {"params": {"direction": 0}}, 400, "direction"),
    (
        "drift-bad-date",
        "GET",
        "/machines/{m}/drift",
        {"params": {"axis": "Z", "term": "dz", "start": "99999-01-01"}},
        400,
        "start",
    ),
    (
        "drift-interpolate-without-position",
        "GET",
        "/machines/{m}/drift",
        {"params": {"axis": "Z", "term": "dz", "interpolate": "true"}},
        400,
        "interpolation needs a position",
    ),
    (
        "condition-unknown",
        "GET",
        "/campaigns/{cid}/conditions",
        {"params": {"column": "torque"}},
        400,
        "query.column.0: Input should be",
    ),
    ("put-not-allowed", "PUT", "/campaigns/{cid}", {"content": BAD_JSON}, 405, "Method Not Allowed"),
    # strict inputs (issue 36): no coercion of text to numbers or of true to 1, no key given twice
    (
        "jobs-holdout-as-text",
        "POST",
        "/jobs",
        {"json": {"kind": "diagnose", "campaign_ids": [1], "holdout_fraction": "0.5"}, "headers": AUTH},
        422,
        "holdout_fraction: Input should be a valid number",
    ),
    (
        "jobs-campaign-true",
        "POST",
        "/jobs",
        {"json": {"kind": "diagnose", "campaign_ids": [True]}, "headers": AUTH},
        422,
        "campaign_ids.0: Input should be a valid integer",
    ),
    (
        "jobs-campaign-as-text",
        "POST",
        "/jobs",
        {"json": {"kind": "diagnose", "campaign_ids": ["1"]}, "headers": AUTH},
        422,
        "campaign_ids.0",
    ),
    (
        "jobs-duplicate-key",
        "POST",
        "/jobs",
        {"content": b'{"kind": "diagnose", "kind": "fit", "campaign_ids": [1]}', "headers": {**AUTH, **JSON}},
        422,
        "the key 'kind' is given twice",
    ),
    (
        "jobs-nested-duplicate-key",
        "POST",
        "/machines/{m}/models",
        {"content": b'{"document": {"machine": "a", "machine": "b"}}', "headers": {**AUTH, **JSON}},
        422,
        "the key 'machine' is given twice",
    ),
    (
        "jobs-nan-literal",
        "POST",
        "/jobs",
        {"content": b'{"kind": "diagnose", "campaign_ids": [1], "holdout_fraction": NaN}', "headers": {**AUTH, **JSON}},
        422,
        "NaN is not a JSON number",
    ),
    (
        "jobs-holdout-denormal",
        "POST",
        "/jobs",
        {"json": {"kind": "diagnose", "campaign_ids": [1], "holdout_fraction": 1e-320}, "headers": AUTH},
        422,
        "holdout_fraction: Input should be greater than or equal to 0.01",
    ),
    (
        "models-source-true",
        "POST",
        "/machines/{m}/models",
        {"json": {"document": {}, "source_campaigns": [True]}, "headers": AUTH},
        422,
        "source_campaigns.0",
    ),
    (
        "probe-number-as-text",
        "POST",
        "/machines/{m}/online/probe",
        {"json": {"x": "1", "y": 0, "z": 0, "dx": 0, "dy": 0, "dz": 0}, "headers": AUTH},
        422,
        "body.x: Input should be a valid number",
    ),
    (
        "probe-time-as-number",
        "POST",
        "/machines/{m}/online/probe",
        {"json": {"x": 1, "y": 0, "z": 0, "dx": 0, "dy": 0, "dz": 0, "measured_at": 1.7e9}, "headers": AUTH},
        422,
        "measured_at: Value error, must be an ISO 8601 date-time string",
    ),
    (
        "probe-time-as-digits",
        "POST",
        "/machines/{m}/online/probe",
        {"json": {"x": 1, "y": 0, "z": 0, "dx": 0, "dy": 0, "dz": 0, "measured_at": "1700000000"}, "headers": AUTH},
        422,
        "measured_at: Value error, must be an ISO 8601 date-time string",
    ),
    *[
        (f"{what}-id-{name}", "GET", template.format(id=text), {}, 400, "must be plain decimal digits")
        for name, text in (("point", "1.0"), ("plus", "+1"), ("space", "%201"), ("underscore", "1_0"), ("zero", "01"))
        for what, template in (
            ("campaign", "/campaigns/{id}"),
            ("version", "/machines/{{m}}/models/{id}"),
            ("job", "/jobs/{id}"),
        )
    ],
    ("limit-point", "GET", "/campaigns", {"params": {"limit": "1.0"}}, 400, "query.limit: Value error"),
    ("buckets-underscore", "GET", "/campaigns/{cid}/temperatures/T1", {"params": {"buckets": "1_0"}}, 400, "buckets"),
]


@pytest.fixture
async def small_client(seeded: Seeded) -> AsyncIterator[httpx.AsyncClient]:
    """A client on an app with a 64 KiB body limit (no background jobs)."""
    app = create_app(seeded.url, TOKEN, run_jobs=False, max_body_bytes=LIMIT)
    async with app.router.lifespan_context(app):
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://test") as c:
            c.app = app  # type: ignore[attr-defined]
            yield c


@pytest.fixture(scope="module", params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def corpus_seeded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Seeded:
    """One seeded database per engine for the whole corpus: each case proves it changed nothing (the row
    counts of every table), so the next case meets the same store as a fresh one."""
    tmp = tmp_path_factory.mktemp("hostile")
    if request.param == "sqlite":
        url = f"sqlite:///{tmp / 'driftlab.sqlite'}"
    else:
        url = request.getfixturevalue("pg_cluster").create_database()
    return seed(url, tmp)


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
async def test_hostile_request(case, corpus_seeded: Seeded) -> None:
    _, method, template, kwargs, status, text = case
    seeded = corpus_seeded
    with connect(seeded.url) as store:
        before = store.table_counts()
        app = create_app(seeded.url, TOKEN, run_jobs=False, max_body_bytes=LIMIT)
        async with app.router.lifespan_context(app):
            async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://test") as client:
                r = await client.request(method, template.format(cid=seeded.campaign_id, m=MACHINE), **kwargs)
        after = store.table_counts()
    assert r.status_code == status, r.text
    if status >= 400:
        assert r.headers["content-type"] == "application/problem+json"
        body = r.json()
        assert body["status"] == status and text in body["detail"], body
    assert after == before


async def _asgi(
    app: Any, method: str, path: str, headers: list[tuple[bytes, bytes]], chunks: list[bytes]
) -> tuple[int, dict[str, Any], int]:
    """Call the app directly; return (status, problem, how many body chunks the app pulled)."""
    pulled = 0
    queue = list(chunks)
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        nonlocal pulled
        pulled += 1
        if queue:
            chunk = queue.pop(0)
            return {"type": "http.request", "body": chunk, "more_body": bool(queue)}
        return {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "headers": headers,
        "server": ("test", 80),
        "client": ("127.0.0.1", 1),
        "root_path": "",
        "app": app,
    }
    await app(scope, receive, send)
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return start["status"], json.loads(body) if body else {}, pulled


async def test_unauthenticated_body_is_never_read(small_client: httpx.AsyncClient) -> None:
    """200 MB announced, no token: 401 and not one chunk pulled from the client."""
    headers = [(b"content-type", b"application/json"), (b"content-length", str(200 << 20).encode())]
    status, problem, pulled = await _asgi(small_client.app, "POST", "/jobs", headers, [b"{" * 1024] * 4)  # type: ignore[attr-defined]
    assert (status, pulled) == (401, 0) and "missing bearer token" in problem["detail"]


async def test_announced_and_streamed_bodies_over_the_limit(small_client: httpx.AsyncClient, store: Store) -> None:
    before = store.table_counts()
    auth = [(b"authorization", f"Bearer {TOKEN}".encode()), (b"content-type", b"application/json")]
    app = small_client.app  # type: ignore[attr-defined]
    status, problem, pulled = await _asgi(
        app, "POST", "/jobs", [*auth, (b"content-length", str(LIMIT + 1).encode())], [b" " * (LIMIT + 1)]
    )
    assert (status, pulled) == (413, 0) and problem["status"] == 413
    # chunked (no Content-Length): refused once the count passes the limit, long before the end
    chunks = [b" " * 4096] * 1000
    status, problem, pulled = await _asgi(app, "POST", "/jobs", auth, chunks)
    assert status == 413 and "larger than the limit" in problem["detail"] and pulled <= LIMIT // 4096 + 2
    status, problem, _ = await _asgi(app, "POST", "/jobs", [*auth, (b"content-length", b"12abc")], [b"{}"])
    assert status == 400 and "Content-Length" in problem["detail"]
    assert store.table_counts() == before


ADDRESSABLE_IDS = ["a", "Z", "9", "vmc.5ax:01", "a-b_c.d:e", "m" * 64, "a..", "x:", "A1-"]


async def test_every_importable_machine_id_is_addressable(
    small_client: httpx.AsyncClient, store: Store, tmp_path: Path
) -> None:
    """An id import accepts is reachable as /machines/{id} (and what the API could not address is refused)."""
    temps, cond, errors = small_frames(scans=8, sweeps=1)
    for k, machine in enumerate(ADDRESSABLE_IDS):
        path = write_bundle(
            tmp_path / f"b{k}", small_meta(machine, f"2026-03-{k + 2:02d}T08:00:00Z"), temps, cond, errors
        )
        store.campaigns.import_bundle(load_bundle(path))
        r = await small_client.get(f"/machines/{quote(machine, safe='')}")
        assert r.status_code == 200 and r.json()["id"] == machine, (machine, r.text)
        r = await small_client.get("/campaigns", params={"machine_id": machine})
        assert r.status_code == 200 and len(r.json()["items"]) == 1, (machine, r.text)


# ----------------------------------------------------------------------------- concurrency


def _race(n: int, work) -> list[Any]:
    """Run ``work(i)`` in n threads released at once; return each result or exception."""
    barrier = threading.Barrier(n)
    out: list[Any] = [None] * n

    def run(i: int) -> None:
        barrier.wait()
        try:
            out[i] = work(i)
        except Exception as exc:  # noqa: BLE001 - the test inspects what each thread got
            out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    return out


def test_concurrent_imports_of_a_new_machine(store: Store, tmp_path: Path) -> None:
    """Different campaigns of one new machine imported at once: every import lands, one machine row."""
    temps, cond, errors = small_frames(scans=8, sweeps=1)
    for rnd in range(3):
        machine = f"race-{rnd}"
        bundles = [
            load_bundle(
                write_bundle(
                    tmp_path / f"r{rnd}-{i}", small_meta(machine, f"2026-04-0{i + 1}T08:00:00Z"), temps, cond, errors
                )
            )
            for i in range(4)
        ]
        results = _race(4, lambda i, bundles=bundles: store.campaigns.import_bundle(bundles[i]))
        assert all(isinstance(r, int) for r in results), results
        assert len(set(results)) == 4
        assert [c.machine_id for c in store.campaigns.summaries(machine)] == [machine] * 4


def test_concurrent_imports_of_one_bundle(store: Store, tmp_path: Path) -> None:
    """The same bundle imported at once: exactly one lands, the others are a clear conflict."""
    temps, cond, errors = small_frames(scans=8, sweeps=1)
    bundle = load_bundle(write_bundle(tmp_path / "same", small_meta("race-same"), temps, cond, errors))
    before = store.table_counts()
    results = _race(4, lambda i: store.campaigns.import_bundle(bundle))
    assert sum(isinstance(r, int) for r in results) == 1, results
    assert all(isinstance(r, ConflictError) for r in results if not isinstance(r, int)), results
    assert store.table_counts()["campaigns"] == before["campaigns"] + 1


async def test_concurrent_deletes_of_one_campaign(
    small_client: httpx.AsyncClient, seeded: Seeded, store: Store
) -> None:
    """Four DELETEs of one campaign at once: exactly one 204, the others 404, every sample gone."""
    path = f"/campaigns/{seeded.campaign_id}"
    answers = await asyncio.gather(*(small_client.delete(path, headers=AUTH) for _ in range(4)))
    codes = sorted(r.status_code for r in answers)
    assert codes == [204, 404, 404, 404], [r.text for r in answers]
    counts = store.table_counts()
    assert counts["campaigns"] == 0 and counts["temperature_samples"] == 0 and counts["error_samples"] == 0


async def test_body_limit_from_the_environment(seeded: Seeded, monkeypatch) -> None:
    """DRIFTLAB_API_MAX_BODY_BYTES sets the limit of an app built without one."""
    monkeypatch.setenv("DRIFTLAB_API_MAX_BODY_BYTES", "100")
    app = create_app(seeded.url, TOKEN, run_jobs=False)
    async with app.router.lifespan_context(app):
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://test") as c:
            r = await c.post("/jobs", content=b" " * 101, headers={**AUTH, **JSON})
            assert r.status_code == 413 and "100 bytes" in r.json()["detail"]
            r = await c.post("/jobs", json={"kind": "sing"}, headers=AUTH)
            assert r.status_code == 422


async def test_a_read_only_store_refuses_writes_in_one_clear_line(db_url: str, tmp_path: Path) -> None:
    """A store the server may read but not write (SQLite opened mode=ro, a PostgreSQL database whose
    transactions are read-only): reads answer, every write is 403 naming the read-only store (not 503
    "try again later", not a 500), and nothing changes."""
    seeded = seed(db_url, tmp_path)
    if db_url.startswith("sqlite"):
        url = f"sqlite:///file:{db_url.removeprefix('sqlite:///')}?mode=ro&uri=true"  # read-only even for root
    else:
        import psycopg

        with psycopg.connect(db_url.replace("postgresql+psycopg://", "postgresql://"), autocommit=True) as conn:
            conn.execute(f'ALTER DATABASE "{db_url.rsplit("/", 1)[1]}" SET default_transaction_read_only = on')
        url = db_url
    with connect(url) as store:
        before = store.table_counts()
    probe = {"x": 1.0, "y": 0.0, "z": 0.0, "dx": 0.0, "dy": 0.0, "dz": 0.0, "temperatures": {"T1": 22.0, "T2": 22.0}}
    writes = [
        ("POST", f"/machines/{MACHINE}/online/probe", {"json": probe}),
        ("DELETE", f"/campaigns/{seeded.campaign_id}", {}),
        ("POST", f"/machines/{MACHINE}/models/{seeded.model_version}/retire", {}),
        ("POST", "/jobs", {"json": {"kind": "fit", "machine_id": MACHINE}}),
    ]
    app = create_app(url, TOKEN, run_jobs=False)
    async with app.router.lifespan_context(app):
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://test") as client:
            assert (await client.get("/campaigns")).status_code == 200
            for method, path, kwargs in writes:
                r = await client.request(method, path, headers=AUTH, **kwargs)
                assert r.status_code == 403, (path, r.text)
                detail = r.json()["detail"]
                assert detail.startswith("writes are refused: the store is read-only (") and "\n" not in detail
                assert "read-only transaction" in detail or "readonly database" in detail, detail
    with connect(url) as store:
        assert store.table_counts() == before
