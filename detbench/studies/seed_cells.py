"""The typed cells of the seed statistics (detbench.studies.seeds), each with its JSON layout (`to_dict`).

`MetricCell`: one metric of one (model, height, range, level) over seeds; `SeedPool`: its seed spread
pooled over the model's heights; `SeedCombined`: one (model, height) over its seeds; `Lead`: the lead
of one model (or height) over another in one cell; `Leader`: a ranking with the lead of its first.
The cells are frozen: pooling over heights makes new ones (dataclasses.replace). Fractions in [0, 1].
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class SeedPool:
    """A cell's seed spread pooled over its model's heights: its own sd, the pooled df, the model."""

    sd_own: float | None
    df: int
    model: str


@dataclass(frozen=True)
class MetricCell:
    """One metric of one (model, height, range, level) over seeds: the seed mean, the seed spread (sd, n - 1;
    its Student-t factor and half-width on the mean), the scene interval of the mean and how it was made, and
    the interval of both. Fractions in [0, 1], rounded to 6 digits; None where nothing is evaluated or no
    interval exists."""

    mean: float | None = None
    sd: float | None = None
    per_seed: tuple[float | None, ...] = ()
    seed_t: float | None = None
    seed_half_width: float | None = None
    scene_ci95: list | None = None
    scene_method: str | None = None
    ci95: list | None = None
    pool: SeedPool | None = None

    def to_dict(self) -> dict:
        d = {"mean": self.mean, "sd": self.sd, "per_seed": list(self.per_seed), "seed_t": self.seed_t,
             "seed_half_width": self.seed_half_width, "scene_ci95": self.scene_ci95,
             "scene_method": self.scene_method, "ci95": self.ci95}
        if self.pool is not None:
            d.update(sd_own=self.pool.sd_own, seed_df=self.pool.df, seed_pool=self.pool.model)
        return d


@dataclass(frozen=True)
class SeedCombined:
    """One (model, height) over its seeds: {range: {level: {metric: MetricCell}}} with the seeds' labels, the
    scene bootstrap's scenes, replicates and confidence; `pooled_over_heights` once pooling has looked at it."""

    num_seeds: int
    seeds: tuple
    num_scenes: int | None
    replicates: int | None
    confidence: float
    results: Mapping[str, Mapping[str, Mapping[str, MetricCell]]]
    pooled_over_heights: bool | None = None

    def cell(self, r: str, lv: str, metric: str) -> MetricCell:
        return self.results[r][lv][metric]

    def to_dict(self) -> dict:
        d = {"num_seeds": self.num_seeds, "seeds": list(self.seeds), "num_scenes": self.num_scenes,
             "replicates": self.replicates, "confidence": self.confidence,
             "seed_spread_measured": self.num_seeds >= 2,
             "results": {r: {lv: {m: c.to_dict() for m, c in by_m.items()} for lv, by_m in by_lv.items()}
                         for r, by_lv in self.results.items()}}
        if self.pooled_over_heights is not None:
            d["seed_spread_pooled_over_heights"] = self.pooled_over_heights
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> SeedCombined:
        """The typed form of a `to_dict` layout (study.json's)."""
        def cell(c: Mapping) -> MetricCell:
            pool = SeedPool(c["sd_own"], c["seed_df"], c["seed_pool"]) if c.get("seed_pool") is not None else None
            return MetricCell(mean=c["mean"], sd=c["sd"], per_seed=tuple(c["per_seed"]), seed_t=c["seed_t"],
                              seed_half_width=c["seed_half_width"], scene_ci95=c["scene_ci95"],
                              scene_method=c["scene_method"], ci95=c["ci95"], pool=pool)

        return cls(num_seeds=d["num_seeds"], seeds=tuple(d["seeds"]), num_scenes=d["num_scenes"],
                   replicates=d["replicates"], confidence=d["confidence"],
                   results={r: {lv: {m: cell(c) for m, c in by_m.items()} for lv, by_m in by_lv.items()}
                            for r, by_lv in d["results"].items()},
                   pooled_over_heights=d.get("seed_spread_pooled_over_heights"))


@dataclass(frozen=True)
class Lead:
    """mean_a - mean_b in one cell: its scene term (interval, method), seed term (t, half-width), the interval of
    both, and the verdict: "ahead" (the interval excludes 0), "not resolved", or "no interval"."""

    diff: float | None
    scene_ci95: list | None
    scene_method: str | None
    seed_t: float | None
    seed_half_width: float | None
    ci95: list | None
    ahead: bool
    verdict: str

    def to_dict(self) -> dict:
        return {"diff": self.diff, "scene_ci95": self.scene_ci95, "scene_method": self.scene_method,
                "seed_t": self.seed_t, "seed_half_width": self.seed_half_width, "ci95": self.ci95,
                "ahead": self.ahead, "verdict": self.verdict}


@dataclass(frozen=True)
class Leader:
    """A ranking of models (key "model") or heights (key "height") by the seed mean of one metric in one cell,
    with the lead of the first over the second."""

    key: str
    range: str
    level: str
    ranking: tuple[dict, ...]  # {key: name, "mean", "ci95", "num_seeds"}, best first
    lead: Lead | None = None

    @property
    def best(self):
        return self.ranking[0][self.key] if self.ranking else None

    @property
    def runner_up(self):
        return self.ranking[1][self.key] if len(self.ranking) > 1 else None

    def to_dict(self) -> dict:
        return {"range": self.range, "level": self.level, "ranking": [dict(e) for e in self.ranking],
                "best": self.best, "runner_up": self.runner_up,
                "lead": None if self.lead is None else self.lead.to_dict()}


__all__ = ["Lead", "Leader", "MetricCell", "SeedCombined", "SeedPool"]
