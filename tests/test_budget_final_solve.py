"""CPU budgets of the no-ids final solve and the pair pre-test of its duplicate merges
(issue 15: backend/cpu_budget.py, reassociate.duplicate_merges, online_final)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.cpu_budget import CpuBudget, sighting_budget
from lampsam.backend.graph_log import run_graph_log_backend
from lampsam.backend.interface import SlamResult
from lampsam.backend.landmark_merge import CoVisibility, merge_pairs, pair_bound_far
from lampsam.backend.noids_offline import association_cost, batch_graph_inputs, result_of
from lampsam.backend.online_final import final_config, final_solve, online_association
from lampsam.backend.reassociate import Sightings, build_graph, duplicate_merges, read_estimate
from lampsam.datasets.graph_text import GraphLog, read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log

#: 200 poses of 0.5 m among 30 trees in a 40 m square (seed 1, as test_online_final.py)
SPEC = LandmarkLogSpec(n_poses=200, n_landmarks=30, extent=40.0, stop_every=0)

NO_PLACE = dataclasses.replace(SlamConfig(), reassociation=dataclasses.replace(
    SlamConfig().reassociation, online_final_held_mixture=False))


class CountingBudget(CpuBudget):
    """A budget spent at its ``n``-th look (``spent`` or ``check``), whatever the CPU:
    the tests cut at a chosen place, independent of the machine's speed (its limit is
    inf, so no CPU timer is armed)."""

    def __init__(self, n: int) -> None:
        super().__init__(float("inf"), "a test budget")
        self.left = n
        self.stages: list[str] = []

    def spent(self, stage: str) -> bool:
        self.stages.append(stage)
        if not self.stopped:
            self.left -= 1
            if self.left > 0:
                return False
            self.stopped = stage
        return True


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[GraphLog, SlamResult, Sightings]:
    path, _ = write_landmark_log(tmp_path_factory.mktemp("budget") / "log.txt", SPEC,
                                 np.random.default_rng(1))
    g = read_graph_text(path)
    online, be = run_graph_log_backend(g, "isam2", NO_PLACE, known_ids=False)
    assert be is not None and online.status == "ok"
    return g, online, online_association(be, online)


def _copy(s: Sightings) -> Sightings:
    return Sightings(s.k.copy(), s.z.copy(), s.r.copy(), s.lid.copy())


def _with_a_duplicate(g: GraphLog, s0: Sightings) -> Sightings:
    """``s0`` with the later half of the most-sighted landmark's sightings moved to a
    new landmark (a copy the final solve's duplicate merges take back)."""
    ids, n = np.unique(s0.lid, return_counts=True)
    lid = s0.lid.copy()
    top = int(ids[np.argmax(n)])
    rows = np.flatnonzero(lid == top)
    lid[rows[len(rows) // 2:]] = int(lid.max()) + 1
    return Sightings(s0.k.copy(), s0.z.copy(), s0.r.copy(), lid)


def test_budget_spent_once_names_the_stage_and_warns(caplog: pytest.LogCaptureFixture) -> None:
    """A spent budget records the first stage that found it spent and warns once,
    naming the stage and the budget; an infinite one is never spent."""
    b = CpuBudget(0.0, "[reassociation] final_solve_cpu_per_sighting")
    b.c0 -= 1.0  # one second of CPU already used
    with caplog.at_level(logging.WARNING):
        assert b.spent("re-association pass 3") and b.spent("final pass")
    assert b.stopped == "re-association pass 3"
    warned = [r.getMessage() for r in caplog.records if "CPU budget" in r.getMessage()]
    assert len(warned) == 1 and "re-association pass 3" in warned[0]
    assert "final_solve_cpu_per_sighting" in warned[0]
    assert not CpuBudget(float("inf")).spent("x")
    assert sighting_budget(0.05, 1000, 30.0) == 50.0
    assert sighting_budget(0.05, 100, 30.0) == 30.0
    assert sighting_budget(float("inf"), 10**6, 30.0) == float("inf")


def test_pair_bound_never_drops_a_pair_inside_the_threshold() -> None:
    """For random joint covariances of two points (seeded), a pair the bound calls far
    is beyond the threshold in the exact squared Mahalanobis distance of ``l_i - l_j``;
    and the bound does call most far pairs far (it is of use)."""
    rng = np.random.default_rng(7)
    far_n = 0
    for _ in range(4000):
        a = rng.normal(size=(4, 4)) * rng.uniform(0.01, 1.0, size=4)
        joint = a @ a.T + 1e-6 * np.eye(4)
        c = joint[:2, :2] + joint[2:, 2:] - joint[:2, 2:] - joint[2:, :2]
        d = rng.normal(size=2) * rng.uniform(0.1, 10.0)
        s_i = np.sqrt(np.linalg.eigvalsh(joint[:2, :2])[-1])
        s_j = np.sqrt(np.linalg.eigvalsh(joint[2:, 2:])[-1])
        far = bool(pair_bound_far(d[None], np.array([s_i]), np.array([s_j]), 13.8)[0])
        if far:
            far_n += 1
            assert float(d @ np.linalg.solve(c, d)) > 13.8
    assert far_n > 500  # measured 924 of 4,000


def test_merge_pairs_with_the_pre_test_gives_the_same_pairs_with_fewer_marginals() -> None:
    """A seeded map of 60 landmarks on a 4 m grid, a few copies 0-0.3 m off their
    original: ``merge_pairs`` with the single-marginal pre-test returns the same pairs
    as without it and asks ``diff_cov`` for fewer than a quarter of the pairs."""
    rng = np.random.default_rng(3)
    grid = np.array([[x, y] for x in range(0, 40, 4) for y in range(0, 24, 4)], float)
    copies = grid[rng.choice(len(grid), 8, replace=False)] + rng.normal(0, 0.15, (8, 2))
    xy = np.r_[grid, copies]
    m = len(xy)
    sig = rng.uniform(0.05, 0.3, m)
    rho = rng.uniform(-0.9, 0.9, m)
    cov = np.zeros((m, 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = sig ** 2, (0.8 * sig) ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = rho * 0.8 * sig ** 2
    asked: list[int] = []

    def diff_cov(ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
        asked.append(len(ia))
        return cov[ia] + cov[ib]  # independent landmarks

    ids, created = np.arange(m) + 100, np.arange(m)
    covis = CoVisibility()
    args = (ids, xy, created, diff_cov, covis.together, 9.21, 18.4, 10.0)
    plain = merge_pairs(*args)
    n_all = asked.pop()
    s_max = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])
    fast = merge_pairs(*args, sigma_max=s_max)
    assert fast == plain and len(plain) >= 4
    assert sum(asked) < n_all / 4


def test_duplicate_merges_are_the_same_with_the_pre_test(
        run: tuple[GraphLog, SlamResult, Sightings], monkeypatch: pytest.MonkeyPatch) -> None:
    """On a seeded log's final-solve graph with a copied landmark, the duplicate merges
    with the single-marginal pre-test are those without it (the copy merged back)."""
    import lampsam.backend.reassociate as ra

    g, online, s0 = run
    s = _with_a_duplicate(g, s0)
    prior, odo = batch_graph_inputs(g, final_config(NO_PLACE))
    graph = build_graph(prior, odo, s)
    v = gtsam.Values()
    for k, p in enumerate(online.poses):
        v.insert(gtsam.symbol("x", k), gtsam.Pose2(*p))
    from lampsam.backend.online_final import online_landmarks

    for i, xy in online_landmarks(online, s).items():
        v.insert(gtsam.symbol("l", i), gtsam.Point2(*xy))
    v = gtsam.LevenbergMarquardtOptimizer(graph, v, gtsam.LevenbergMarquardtParams()).optimize()
    _, lms = read_estimate(v, len(g.pose_ids), np.unique(s.lid).tolist())
    cfg = NO_PLACE.association
    with_test = duplicate_merges(graph, v, lms, s, cfg.gate(2), cfg.new_threshold(2), 10.0)
    monkeypatch.setattr(ra, "landmark_sigma_max", lambda *a, **k: None)
    without = duplicate_merges(graph, v, lms, s, cfg.gate(2), cfg.new_threshold(2), 10.0)
    assert with_test == without and int(s.lid.max()) in with_test
    # the pairs' blocks from chunked joint marginals are the pair-by-pair ones
    marg = gtsam.Marginals(graph, v)
    ids = np.array(sorted(lms))
    a = np.repeat(ids[:12], 3)
    b = np.array([ids[j + d] for j in range(12) for d in (1, 5, 9)])
    a, b = np.r_[a, b], np.r_[b, a]  # either key order
    monkeypatch.setattr(ra, "JOINT_CHUNK", 8)  # several chunks
    got = ra.pairs_diff_cov(marg, a, b)
    want = np.array([ra.pair_diff_cov(marg, int(x), int(y)) for x, y in zip(a, b, strict=True)])
    assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()


def test_a_final_solve_past_its_budget_keeps_the_answer_before_the_cut(
        run: tuple[GraphLog, SlamResult, Sightings]) -> None:
    """A budget spent before the first re-association pass: the answer is the online
    association at its optimum under the stated noise (its ``C`` computed here
    independently), ``stopped`` names the pass, and the result says so; a budget spent
    inside the second pass's duplicate merges keeps the first pass's association (the
    answer of a solve allowed one pass)."""
    g, online, s0 = run
    cut = final_solve(g, NO_PLACE, online, _copy(s0), place=False, budget=CountingBudget(1))
    assert cut.stopped == "re-association pass 1" and not cut.passes and not cut.moves
    assert np.array_equal(cut.sightings.lid, s0.lid)
    prior, odo = batch_graph_inputs(g, final_config(NO_PLACE))
    graph = build_graph(prior, odo, s0)
    lm = gtsam.LevenbergMarquardtOptimizer(graph, cut.values, gtsam.LevenbergMarquardtParams())
    v = lm.optimize()
    c_new = NO_PLACE.association.new_threshold(2)
    chi2 = 2.0 * (float(graph.error(v)) - float(prior.error(v)))
    dropped = sum(len(x) for x in g.sightings) - len(s0.k)
    want = association_cost(chi2, len(np.unique(s0.lid)), dropped, c_new)
    assert cut.cost == pytest.approx(want, rel=1e-6)
    res = result_of(g, final_config(NO_PLACE), cut, {}, 0.0, 0.0)
    assert res.extra["noids_stopped_by_budget"] == 1.0

    # a copy: pass 1 merges it; cut at the first look inside pass 2's duplicate merges
    s = _with_a_duplicate(g, s0)
    free = CountingBudget(10**9)
    final_solve(g, NO_PLACE, online, _copy(s), place=False, budget=free)
    j = free.stages.index("re-association pass 2")
    assert free.stages[j + 1].startswith("duplicate merges")
    cut2 = final_solve(g, NO_PLACE, online, _copy(s), place=False, budget=CountingBudget(j + 2))
    assert cut2.stopped == free.stages[j + 1] and len(cut2.passes) == 1
    one = dataclasses.replace(NO_PLACE, reassociation=dataclasses.replace(
        NO_PLACE.reassociation, online_final_passes=1, cost_moves=False, final_pass=False))
    ref = final_solve(g, one, online, _copy(s), place=False)
    assert np.array_equal(cut2.sightings.lid, ref.sightings.lid)
    assert cut2.cost == pytest.approx(ref.cost, rel=1e-9)
    assert len(np.unique(cut2.sightings.lid)) == len(np.unique(s.lid)) - 1


def test_the_picker_reports_a_final_solve_stopped_by_its_budget(
        run: tuple[GraphLog, SlamResult, Sightings], tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    """With ``final_solve_cpu_per_sighting`` and the floor tiny, each candidate's final
    solve stops (a warning names the stage and the option); the candidate is still
    ``ok`` with its answer, its row says where it stopped, the chosen answer's
    ``noids_stopped_by_budget`` is 1 and no placement runs."""
    from lampsam.backend.online_final import run_online_picker

    g, _, _ = run
    cfg = dataclasses.replace(SlamConfig(), reassociation=dataclasses.replace(
        SlamConfig().reassociation, online_candidates=("defaults",),
        final_solve_cpu_per_sighting=1e-12, online_candidate_cpu_floor_s=0.0))
    with caplog.at_level(logging.WARNING):
        final, _, cands, i = run_online_picker(g, "isam2", cfg)
    c = cands[i]
    assert c.status == "ok" and c.solve is not None and c.solve.stopped
    assert c.row()["stopped_by_budget"] == c.solve.stopped
    assert final.extra["noids_stopped_by_budget"] == 1.0
    assert "noids_held_placed" not in final.extra
    msgs = [r.getMessage() for r in caplog.records]
    assert any("stopped by its CPU budget" in m and "final_solve_cpu_per_sighting" in m
               for m in msgs)
    assert any("left-out sightings are not placed" in m for m in msgs)


def test_the_gate_prefetches_planar_joint_marginals_equal_to_per_landmark_queries(
        run: tuple[GraphLog, SlamResult, Sightings], monkeypatch: pytest.MonkeyPatch) -> None:
    """Online iSAM2 without ids on the seeded log: each keyframe's planar landmarks the
    screen leaves to the joint marginal are fetched in one query (they were asked one by
    one: the prefetch skipped NaN screen distances and sized Point2 blocks as 3-D), and
    the cached blocks equal a per-landmark ``jointMarginalCovariance`` to 1e-8."""
    from gtsam.symbol_shorthand import X

    from lampsam.backend.gate_exact import ExactGate

    g, _, _ = run
    orig = ExactGate._prefetch_joint
    checked: list[int] = []

    def check(self, k, obs, screened):  # type: ignore[no-untyped-def]
        n = orig(self, k, obs, screened)
        if n and len(checked) < 40:
            for lid, (s_kk, s_kl, s_ll) in list(self._joint_cache.items())[:3]:
                lm = self._landmarks[lid]
                full = np.asarray(self.isam.jointMarginalCovariance(
                    [X(k), *self.handlers[lm.kind].keys(lm)]).fullMatrix())
                scale = np.abs(full).max()
                np.testing.assert_allclose(s_kk, full[:3, :3], rtol=0, atol=1e-8 * scale)
                np.testing.assert_allclose(s_kl, full[:3, 3:], rtol=0, atol=1e-8 * scale)
                np.testing.assert_allclose(s_ll, full[3:, 3:], rtol=0, atol=1e-8 * scale)
                checked.append(len(s_ll))
        return n

    monkeypatch.setattr(ExactGate, "_prefetch_joint", check)
    online, _ = run_graph_log_backend(g, "isam2", NO_PLACE, known_ids=False)
    assert online.status == "ok"
    assert len(checked) >= 20 and set(checked) == {2}


def test_interrupt_past_stops_a_stage_without_looks_of_its_own() -> None:
    """A busy stage that never looks at its budget is stopped by the CPU timer once the
    budget is spent; the stage is recorded and the previous SIGPROF handler is back;
    a spent budget raises before the stage starts; no budget arms nothing."""
    import signal

    from lampsam.backend.cpu_budget import BudgetSpent, interrupt_past

    before = signal.getsignal(signal.SIGPROF)
    b = CpuBudget(0.2, "a test budget")
    n = 0
    with pytest.raises(BudgetSpent, match="busy stage"), interrupt_past(b, "busy stage"):
        while n < 10**10:
            n += 1
    assert b.stopped == "busy stage" and n < 10**10
    assert signal.getsignal(signal.SIGPROF) is before
    assert signal.getitimer(signal.ITIMER_PROF) == (0.0, 0.0)
    with pytest.raises(BudgetSpent), interrupt_past(b, "next stage"):
        raise AssertionError("not reached")
    with interrupt_past(None, "free"):
        n = -1
    assert n == -1


def test_a_final_pass_stopped_inside_keeps_the_answer_before_it(
        run: tuple[GraphLog, SlamResult, Sightings], monkeypatch: pytest.MonkeyPatch) -> None:
    """The final pass (its moves have no look at the budget) stopped inside by the timer:
    the answer is the one before the final pass, marked stopped there."""
    import time

    import lampsam.backend.noids_offline as no
    from lampsam.backend.noids_offline import final_pass

    g, online, s0 = run
    base = final_solve(g, NO_PLACE, online, _copy(s0), place=False)

    def slow(*a: object, **k: object) -> None:
        t0 = time.process_time()
        while time.process_time() - t0 < 30.0:  # CPU-bound, never looks at a budget
            pass
        raise AssertionError("not stopped")

    monkeypatch.setattr(no, "_final_pass", slow)
    b = CpuBudget(0.3, "a test budget")
    out = final_pass(g, final_config(NO_PLACE), base, budget=b)
    assert out.stopped == "final pass" and out.cost == base.cost
    assert np.array_equal(out.sightings.lid, base.sightings.lid)


def test_cli_says_the_final_solve_was_stopped_by_its_budget(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``lampsam slam LOG --no-ids``: with a tiny final-solve budget the printed line says
    the final solve was stopped, and ``summary.json`` has the flag and the stage."""
    import json

    from lampsam.cli import main

    path, _ = write_landmark_log(tmp_path / "log.txt", SPEC, np.random.default_rng(1))
    (tmp_path / "c.toml").write_text(
        '[reassociation]\nonline_candidates = ["defaults"]\n'
        "final_solve_cpu_per_sighting = 1e-12\nonline_candidate_cpu_floor_s = 0.0\n")
    out = tmp_path / "out"
    assert main(["slam", str(path), "--no-ids", "--backend", "isam2", "--config",
                 str(tmp_path / "c.toml"), "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["noids_stopped_by_budget"] == 1.0
    assert s["online_picker"]["candidates"][0]["stopped_by_budget"] == "re-association pass 1"
    assert "STOPPED by its CPU budget" in capsys.readouterr().out
