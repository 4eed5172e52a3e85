"""``GET /v1/metrics`` (JSON) and ``GET /metrics`` (Prometheus text format): training progress,
clustering quality, and the service's own request counters."""

from __future__ import annotations

from typing import Any, Iterator

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from ..deps import ERROR_RESPONSES, ApiState, api_state, current_snapshot, require_token, snapshot_json
from ..schemas import TrainingMetrics
from ..snapshot import Snapshot, SnapshotCache

router = APIRouter(tags=["metrics"], dependencies=[Depends(require_token)])

SUCCESS, RETURN = "success/", "return/"


def _num(v: Any) -> float | int | None:
    return v if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def training_metrics(snap: Snapshot) -> TrainingMetrics:
    """The JSON metrics view of a snapshot."""
    m = snap.metrics
    progress: dict[str, Any] = dict(m.get("progress") or {})

    per_task = {**snap.per_task, **{k: v for k, v in progress.items() if k.startswith((SUCCESS, RETURN))}}

    def num(key: str) -> Any:
        return _num(progress.get(key))

    def as_int(key: str) -> int | None:
        v = num(key)
        return None if v is None else int(v)

    return TrainingMetrics(
        iteration=as_int("iteration"),
        episodes=as_int("episodes"),
        env_steps=as_int("env_steps"),
        env_steps_per_s=snap.env_steps_per_s,
        ari=m.get("ari"),
        episodes_labelled=m.get("episodes_labelled"),
        num_policies=int(m.get("num_policies", 0)),
        current_policy_id=m.get("current_policy_id"),
        success={k[len(SUCCESS) :]: _num(v) for k, v in sorted(per_task.items()) if k.startswith(SUCCESS)},
        returns={k[len(RETURN) :]: _num(v) for k, v in sorted(per_task.items()) if k.startswith(RETURN)},
        policy_counts={str(k): int(v) for k, v in (m.get("policy_counts") or {}).items()},
        confusion=m.get("confusion") or {},
        progress=progress,
        evaluation={k: _num(v) for k, v in sorted((m.get("evaluation") or {}).items())},
        as_of=snap.as_of,
    )


@router.get("/v1/metrics", response_model=TrainingMetrics, summary="Training metrics (JSON)", responses=ERROR_RESPONSES)
async def metrics_json(snap: Snapshot = Depends(current_snapshot)) -> Response:
    return snapshot_json(snap, "metrics", lambda: training_metrics(snap))


@router.get(
    "/metrics",
    summary="Training metrics and request counters in Prometheus text format",
    response_class=Response,
    responses={
        200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus exposition format."},
        **{k: v for k, v in ERROR_RESPONSES.items() if k in (401,)},
    },
)
async def metrics_prometheus(state: ApiState = Depends(api_state)) -> Response:
    registry: CollectorRegistry = state.prometheus  # type: ignore[attr-defined]
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


class TrainingCollector(Collector):
    """Training metrics read from the latest snapshot at scrape time (names and types: docs/guide/api.md).

    Running counts are counters (``_total``; take ``rate()`` for speeds), levels are gauges, rates of
    success are ``_ratio`` gauges in 0..1, ids are labels (``covers_current_policy_info``)."""

    def __init__(self, cache: SnapshotCache) -> None:
        self.cache = cache

    def collect(self) -> Iterator[Metric]:
        snap = self.cache.latest
        if snap is None:
            return
        t = training_metrics(snap)
        for name, value, doc in (
            ("covers_iterations", t.iteration, "Training iterations (sample, assign, update, publish) done."),
            ("covers_episodes", t.episodes, "Episodes run."),
            ("covers_env_steps", t.env_steps, "Environment steps run."),
        ):
            if value is not None:
                yield CounterMetricFamily(name, doc, value=float(value))
        for name, value, doc in (
            ("covers_adjusted_rand_index", t.ari, "Adjusted Rand Index between policy ids and true task groups."),
            ("covers_policies", t.num_policies, "Policies in the bank."),
            ("covers_snapshot_age_seconds", self.cache.age_s(), "Age of the state served."),
        ):
            if value is not None:
                yield GaugeMetricFamily(name, doc, value=float(value))
        if t.current_policy_id is not None:
            info = GaugeMetricFamily(
                "covers_current_policy_info", "The policy being trained (always 1; its id is the label).",
                labels=["policy_id"],
            )  # fmt: skip
            info.add_metric([str(t.current_policy_id)], 1.0)
            yield info
        for name, values, doc in (
            ("covers_success_ratio", t.success, "Latest success rate per base task (0..1)."),
            ("covers_episode_return", t.returns, "Latest average episode return per base task."),
        ):
            g = GaugeMetricFamily(name, doc, labels=["task"])
            for task, v in values.items():
                if v is not None:
                    g.add_metric([task], float(v))
            yield g
        yield from _evaluation_gauges(t.evaluation)
        episodes = CounterMetricFamily(
            "covers_policy_episodes", "Episodes assigned per policy.", labels=["policy_id"]
        )
        buffers = GaugeMetricFamily(
            "covers_policy_buffer_observations", "Initial observations held in each policy's buffer.",
            labels=["policy_id"],
        )  # fmt: skip
        for p in snap.summary.get("policies", []):
            episodes.add_metric([str(p["policy_id"])], float(p.get("episodes_assigned", 0)))
            buffers.add_metric([str(p["policy_id"])], float(p.get("buffer_size", 0)))
        yield episodes
        yield buffers


EVAL_SCALARS = (
    ("covers_eval_average_success_ratio", "eval/average_success",
     "Evaluation: mean greedy success over groups seen (0..1)."),
    ("covers_eval_zero_shot_success_ratio", "eval/zero_shot_success",
     "Evaluation: greedy success on held-out (task, g) pairs (0..1)."),
    ("covers_eval_average_forgetting_ratio", "eval/average_forgetting",
     "Evaluation: mean forgetting over groups (a difference of success rates)."),
)  # fmt: skip
EVAL_PER_TASK = (
    ("covers_eval_success_ratio", "eval/success/", "Evaluation: greedy success per base task (bank's choice, 0..1)."),
    ("covers_eval_success_worst_ratio", "eval/success_worst/",
     "Evaluation: greedy success on the base task's worst (task, g) pair (bank's choice, 0..1)."),
    ("covers_eval_forgetting_ratio", "eval/forgetting/",
     "Evaluation: best earlier success minus latest, per base task."),
)  # fmt: skip


def _evaluation_gauges(evaluation: dict[str, Any]) -> Iterator[GaugeMetricFamily]:
    for name, key, doc in EVAL_SCALARS:
        if evaluation.get(key) is not None:
            yield GaugeMetricFamily(name, doc, value=float(evaluation[key]))
    for name, prefix, doc in EVAL_PER_TASK:
        g = GaugeMetricFamily(name, doc, labels=["task"])
        for key, v in evaluation.items():
            if key.startswith(prefix) and v is not None:
                g.add_metric([key[len(prefix) :]], float(v))
        yield g


class RequestMetrics:
    """Request counters and latencies of the service itself."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.requests = Counter(
            "covers_api_requests", "HTTP requests answered.", ["method", "route", "status"], registry=registry
        )
        self.latency = Histogram(
            "covers_api_request_duration_seconds",
            "Time to answer an HTTP request.",
            ["method", "route"],
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0),
            registry=registry,
        )

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)


def make_registry(cache: SnapshotCache) -> tuple[CollectorRegistry, RequestMetrics]:
    """A registry for one app: training gauges plus request metrics."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(TrainingCollector(cache))
    return registry, RequestMetrics(registry)
