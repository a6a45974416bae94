"""The notebook API: a driftlab server's campaigns, readings and models as pandas objects (docs/notebook.md).

``driftlab.connect(url)`` opens a read-only client of the REST API (docs/api.md) for an engineer in
Jupyter or a script: no internal imports, no database URL, only what the server serves.

>>> lab = driftlab.connect("http://127.0.0.1:8765")
>>> lab.campaigns()                       # one row per campaign, indexed by its id
>>> lab.temperatures(1)                   # time-indexed (UTC), one column per channel, °C
>>> lab.errors(1, axis="Z", term="dz")    # one row per measured error sample, with its unit
>>> model = lab.model("vmc-5ax-01")       # the machine's current model
>>> model.summary()                       # one row per term model: RMSE in µm or µrad
>>> model.predict(lab.temperatures(1), pose=(127, 127, -150, 0, 0))   # work-space errors, µm and µrad

Units (labelled, never implied): temperatures are °C (``attrs["unit"]``); error samples carry a
``unit`` column (mm for translations, rad for rotations, as stored) and ``value_um_or_urad`` beside
it; predictions are columns named with their unit (``dx_um`` ... ``gamma_urad``). Times are both
``time_s`` (seconds since the campaign started) and a UTC ``time`` index.

The prediction is the model document's own (``models.document.predict_workspace_errors``: the link
models through the HTM chain, eq. 4.12), the same the compensator corrects with.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import pandas as pd

from driftlab.errors import NotFoundError, ValidationError
from driftlab.labels import display_unit, feature_label
from driftlab.vocabulary import AXES, ROTATIONS, TERMS

#: rows per page asked of the paged histories (the API's largest page, docs/api.md)
PAGE = 10_000
#: the work-space error columns of a prediction, with their units (µm for translations, µrad for rotations)
PREDICTION_COLUMNS = tuple(f"{t}_{'urad' if t in ROTATIONS else 'um'}" for t in TERMS)


def connect(url: str, token: str | None = None, *, client: httpx.Client | None = None, timeout_s: float = 30.0) -> Lab:
    """Return a client of the driftlab API at ``url`` (``token``: DRIFTLAB_API_TOKEN, only for private servers).

    ``client`` is an httpx.Client to use instead (its base URL is then the server's), e.g. one over an
    ASGI app in a test, or with a proxy.
    """
    if client is None:
        if not url.startswith(("http://", "https://")):
            raise ValidationError(f"{url!r}: give the API's base URL, http://HOST:PORT")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        client = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout_s)
    return Lab(client)


@dataclass
class Lab:
    """A driftlab server seen from a notebook: every method returns pandas objects (or a Model)."""

    client: httpx.Client

    def __enter__(self) -> Lab:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the HTTP connection."""
        self.client.close()

    def _get(self, path: str, **params: Any) -> Any:
        """Return the JSON of GET ``path``; a problem response becomes one DriftlabError line."""
        try:
            r = self.client.get(path, params={k: v for k, v in params.items() if v is not None})
        except httpx.HTTPError as exc:
            raise ValidationError(f"{self.client.base_url}{path}: {type(exc).__name__}: {exc}") from None
        if r.status_code == 404:
            raise NotFoundError(_problem(r))
        if r.status_code >= 400:
            raise ValidationError(f"{path}: HTTP {r.status_code}: {_problem(r)}")
        return r.json()

    def campaigns(self, machine: str | None = None) -> pd.DataFrame:
        """Return the campaigns (of one machine, or all), indexed by id, with their sizes and UTC start."""
        rows: list[dict[str, Any]] = []
        offset = 0
        while True:
            page = self._get("/campaigns", machine_id=machine, limit=1000, offset=offset)
            rows.extend(page["items"])
            if len(page["items"]) < 1000:
                break
            offset += 1000
        cols = ["id", "machine_id", "name", "started_at", "status", "source", "channels", "scans", "error_samples"]
        frame = pd.DataFrame(rows, columns=list(dict.fromkeys([*cols, *(rows[0] if rows else [])])))
        frame["started_at"] = pd.to_datetime(frame["started_at"], utc=True)
        return frame.set_index("id")

    def campaign(self, campaign_id: int) -> dict[str, Any]:
        """Return one campaign's detail (stages, channels, campaign.json) as the API gives it."""
        return dict(self._get(f"/campaigns/{int(campaign_id)}"))

    def channels(self, campaign_id: int) -> pd.DataFrame:
        """Return a campaign's thermocouple sites (name, location, structure, room or not), in scan order."""
        detail = self.campaign(campaign_id)
        return pd.DataFrame(detail.get("channel_list") or []).set_index("name")

    def _pages(self, path: str, key: str, **params: Any) -> Iterator[list[dict[str, Any]]]:
        """Yield the pages of a cursor-paged history."""
        cursor = None
        while True:
            page = self._get(path, limit=PAGE, cursor=cursor, **params)
            yield page[key]
            cursor = page.get("next_cursor")
            if not cursor:
                return

    def temperatures(
        self,
        campaign_id: int,
        channels: Sequence[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
    ) -> pd.DataFrame:
        """Return a campaign's temperatures (°C): a UTC time index, ``time_s``, one column per channel.

        ``channels`` defaults to every channel of the campaign (room channels included), in scan order;
        a missing reading is NaN.
        """
        detail = self.campaign(campaign_id)
        names = list(channels) if channels is not None else [c["name"] for c in detail.get("channel_list") or []]
        known = {c["name"] for c in detail.get("channel_list") or []}
        unknown = [c for c in names if c not in known]
        if unknown:
            raise NotFoundError(f"campaign {campaign_id} has no channel {', '.join(unknown)}")
        series = {}
        for ch in names:
            points = [
                p
                for page in self._pages(
                    f"/campaigns/{int(campaign_id)}/temperatures/{ch}", "points", start_s=start_s, end_s=end_s
                )
                for p in page
            ]
            series[ch] = pd.Series(
                [np.nan if p["value"] is None else p["value"] for p in points],
                index=pd.Index([p["time_s"] for p in points], dtype=float),
                dtype=float,
            )
        frame = pd.DataFrame(series)
        frame.index.name = "time_s"
        frame = frame.sort_index().reset_index()
        frame.index = pd.DatetimeIndex(
            pd.to_datetime(detail["started_at"], utc=True) + pd.to_timedelta(frame["time_s"], unit="s"), name="time"
        )
        frame.attrs.update({"unit": "°C", "campaign_id": int(campaign_id)})
        return frame

    def errors(
        self,
        campaign_id: int,
        axis: str | None = None,
        term: str | None = None,
        direction: int | None = None,
    ) -> pd.DataFrame:
        """Return a campaign's measured error samples, one row each, in measuring order, with their units.

        Columns: ``time_s``, ``axis``, ``term``, ``position`` (mm, or degrees on A and B), ``direction``,
        ``sweep``, ``value`` with its ``unit`` (mm or rad, as stored), ``value_um_or_urad``; a UTC ``time``
        index.
        """
        if axis is not None and axis not in AXES:
            raise ValidationError(f"axis must be one of {' '.join(AXES)}, got {axis!r}")
        if term is not None and term not in TERMS:
            raise ValidationError(f"term must be one of {' '.join(TERMS)}, got {term!r}")
        detail = self.campaign(campaign_id)
        rows = [
            r
            for page in self._pages(
                f"/campaigns/{int(campaign_id)}/errors", "items", axis=axis, term=term, direction=direction
            )
            for r in page
        ]
        cols = ["seq", "time_s", "axis", "term", "position", "direction", "sweep", "flags", "value"]
        frame = pd.DataFrame(rows, columns=cols)
        rotation = frame["term"].isin(list(ROTATIONS))
        frame["unit"] = np.where(rotation, "rad", "mm")
        frame["value_um_or_urad"] = frame["value"].astype(float) * np.where(rotation, 1e6, 1e3)
        frame.index = pd.DatetimeIndex(
            pd.to_datetime(detail["started_at"], utc=True) + pd.to_timedelta(frame["time_s"].astype(float), unit="s"),
            name="time",
        )
        frame.attrs.update({"campaign_id": int(campaign_id), "position_unit": "mm; degrees on A and B"})
        return frame

    def model(self, machine: str, version: int | None = None) -> Model:
        """Return the machine's current model (or one ``version``) with its ETag."""
        path = f"/machines/{machine}/model/current" if version is None else f"/machines/{machine}/models/{int(version)}"
        try:
            r = self.client.get(path)
        except httpx.HTTPError as exc:
            raise ValidationError(f"{self.client.base_url}{path}: {type(exc).__name__}: {exc}") from None
        if r.status_code == 404:
            raise NotFoundError(_problem(r))
        if r.status_code >= 400:
            raise ValidationError(f"{path}: HTTP {r.status_code}: {_problem(r)}")
        body = r.json()
        return Model(body.get("document") or body, etag=r.headers.get("ETag", ""))


@dataclass
class Model:
    """A fitted model document with what a notebook asks of it: ``summary()`` and ``predict()``."""

    document: dict[str, Any]
    etag: str = ""
    _validated: Any = field(default=None, repr=False)

    @property
    def machine(self) -> str:
        """Return the machine the model is of."""
        return str(self.document.get("machine", ""))

    @property
    def version(self) -> int | None:
        """Return the model's registry version."""
        v = self.document.get("version")
        return None if v is None else int(v)

    @property
    def channels(self) -> list[str]:
        """Return the thermocouples the model reads."""
        return list(self.document.get("inputs") or {})

    def _doc(self) -> Any:
        """Return the validated document (``models.document.ModelDocument``), validated once."""
        if self._validated is None:
            from driftlab.models.document import validate_document  # lazy: the modelling stack

            self._validated = validate_document(self.document)
        return self._validated

    def summary(self) -> pd.DataFrame:
        """Return one row per term model: element, parameter, features in words, RMSE in µm or µrad."""
        rows = []
        for t in self.document.get("terms") or []:
            k, unit = display_unit(str(t["param"]))
            stats = t.get("statistics") or {}
            held = stats.get("rmse_holdout")
            rows.append(
                {
                    "element": t["element"],
                    "param": t["param"],
                    "axis": t.get("axis"),
                    "term": t.get("term"),
                    "features": "; ".join(feature_label(str(f.get("name", ""))) for f in t.get("features") or []),
                    "n_features": len(t.get("features") or []),
                    "rmse_train": float(stats.get("rmse_train", math.nan)) * k,
                    "rmse_holdout": math.nan if held is None else float(held) * k,
                    "unit": unit,
                    "r2": stats.get("r2"),
                }
            )
        frame = pd.DataFrame(rows)
        frame.attrs.update({"machine": self.machine, "version": self.version, "etag": self.etag})
        return frame

    def predict(
        self,
        temperatures: pd.DataFrame | Mapping[str, float],
        pose: Sequence[float] | pd.DataFrame = (0.0, 0.0, 0.0, 0.0, 0.0),
        direction: int | None = None,
    ) -> pd.DataFrame:
        """Return the work-space errors the model predicts (``dx_um`` ... ``gamma_urad``), one row per reading.

        ``temperatures``: a frame as ``Lab.temperatures`` returns (°C, with ``time_s`` for lagged terms)
        or one reading per channel. ``pose``: X Y Z (mm) A B (degrees), one for every row, or a frame
        with those columns aligned with ``temperatures``. ``direction``: +1/-1 approach, None the mean.
        """
        from driftlab.models.document import predict_workspace_errors  # lazy: the modelling stack

        frame = pd.DataFrame([dict(temperatures)]) if isinstance(temperatures, Mapping) else temperatures
        missing = [c for c in self.channels if c not in frame.columns]
        if missing:
            raise ValidationError(f"the temperatures lack the model's channels {', '.join(missing)}")
        n = len(frame)
        if isinstance(pose, pd.DataFrame):
            if len(pose) != n:
                raise ValidationError(f"pose has {len(pose)} rows, the temperatures {n}")
            q = pose[list(AXES)].to_numpy(float)
        else:
            if len(pose) != 5:
                raise ValidationError(f"pose must be X, Y, Z (mm), A, B (degrees), got {len(pose)} numbers")
            q = np.tile(np.asarray(pose, float), (n, 1))
        q = q.copy()
        q[:, 3:] = np.deg2rad(q[:, 3:])  # the chain takes the rotary axes in rad (eq. 4.12)
        d = None if direction is None else np.full(n, int(direction))
        inputs = frame[[c for c in (*self.channels, "time_s") if c in frame.columns]].reset_index(drop=True)
        # a row with a missing reading of a model channel has no prediction (NaN), the others are predicted
        ok = np.isfinite(inputs[self.channels].to_numpy(float)).all(axis=1)
        values = np.full((n, len(TERMS)), np.nan)
        if ok.any():
            rows = inputs[ok].reset_index(drop=True)
            values[ok] = predict_workspace_errors(self._doc(), rows, q[ok], None if d is None else d[ok])
        scale = np.array([1e6 if t in ROTATIONS else 1e3 for t in TERMS])
        out = pd.DataFrame(values * scale, columns=list(PREDICTION_COLUMNS), index=frame.index)
        out.attrs.update({"machine": self.machine, "version": self.version, "unit": "µm, µrad"})
        return out


def _problem(r: httpx.Response) -> str:
    """Return the one-line detail of an API problem response (or its status)."""
    try:
        body = r.json()
    except ValueError:
        return f"HTTP {r.status_code}"
    if not isinstance(body, dict):
        return str(body)
    return str(body.get("detail") or body.get("title") or f"HTTP {r.status_code}")
