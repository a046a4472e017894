"""Benchmark: built-in vs CustomFactor, per observation vs per frame (DESIGN sec. 6).

A synthetic planar drive of ``--poses`` poses under a ceiling with landmarks on a
grid; each pose sees its ``--per-pose`` nearest landmarks (default 2,000 poses x 5 =
10,000 observations). Timed, median of ``--repeats`` runs:

* ``graph.linearize(values)`` on a Python-owned ``Values`` (no copy per callback);
* ``LevenbergMarquardtOptimizer`` for ``--iterations`` iterations from a perturbed start
  (callbacks from inside the optimizer: the ``Values`` copy per call).

Cases:

1. lamp/corner position: built-in ``PlanarProjectionFactor2`` (reference) vs a
   ``CustomFactor`` over ``project_point`` per observation;
2. inverse-depth corners: one ``CustomFactor`` per observation vs one per frame;
3. lamp axes: per observation vs per frame;
4. corner parametrisation, full LM to convergence on noisy data: inverse depth
   (per-frame ``CustomFactor``) vs ``Point3`` with the built-in projection and a height
   prior; time, pose and corner errors against the truth.

Ratios are against the reference of each case measured in the same run. The machine
is shared, so absolute times are inflated; ratios are more stable.

Usage: ``.venv/bin/python scripts/bench/bench_factors.py [--poses 2000 --per-pose 5]``
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, C, L, X

from lampsam.factors.axis_factors import (
    AxisObservation,
    axis_anchor_prior,
    lamp_axis_between_factor,
    lamp_axis_factor,
    lamp_axis_frame_factor,
)
from lampsam.factors.ceiling import (
    HeightPrior,
    init_point_from_observation,
    inverse_depth_to_point,
    project_inverse_depth,
    project_point,
)
from lampsam.factors.gtsam_factors import (
    height_prior_factor,
    noise_model,
    odometry_factor,
    projection_factor,
)
from lampsam.factors.inverse_depth_factors import (
    InverseDepthObservation,
    inverse_depth_factor,
    inverse_depth_first_sight_prior,
    inverse_depth_frame_factor,
)
from lampsam.factors.motion import accumulate_odometry

OFFSET = np.array([0.1, 0.0, 0.3])
COV_M = np.eye(2) * 0.005**2


def _median_time(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _world(n_poses: int, rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    """A lawn-mower drive over a 20 m x 10 m room and a 1 m landmark grid at 2.6-2.8 m."""
    t = np.linspace(0.0, 1.0, n_poses)
    x = 20.0 * t
    y = 4.0 * np.sin(2.0 * np.pi * 3.0 * t)
    theta = np.arctan2(np.gradient(y), np.gradient(x))
    poses = [np.array([a, b, c]) for a, b, c in zip(x, y, theta, strict=True)]
    gx, gy = np.meshgrid(np.arange(-0.5, 21.0, 1.0), np.arange(-5.5, 6.0, 1.0))
    lms = np.column_stack([gx.ravel(), gy.ravel(), rng.uniform(2.6, 2.8, gx.size)])
    return poses, lms


def _odometry(graph: gtsam.NonlinearFactorGraph, poses: list[np.ndarray]) -> None:
    graph.add(
        gtsam.PriorFactorPose2(
            X(0), gtsam.Pose2(*poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)
        )
    )
    for i in range(1, len(poses)):
        delta = np.asarray(gtsam.Pose2(*poses[i - 1]).between(gtsam.Pose2(*poses[i])).matrix())
        d = np.array([delta[0, 2], delta[1, 2], np.arctan2(delta[1, 0], delta[0, 0])])
        cov = accumulate_odometry(np.array([0.01]), np.array([0.01]), 0.33, 1e-3, 1e-3)[1]
        graph.add(odometry_factor(X(i - 1), X(i), d, cov))


def _visible(pose: np.ndarray, lms: np.ndarray, k: int) -> np.ndarray:
    d = np.linalg.norm(lms[:, :2] - pose[:2], axis=1)
    return np.argsort(d)[:k]


def _custom_projection(pose_key: int, point_key: int, m: np.ndarray) -> gtsam.CustomFactor:
    meas = m.copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> np.ndarray:
        p = values.atPose2(this.keys()[0])
        pred, j_pose, j_point = project_point(
            np.array([p.x(), p.y(), p.theta()]), values.atPoint3(this.keys()[1]), OFFSET
        )
        if H is not None:
            H[0], H[1] = j_pose, j_point
        return pred - meas

    return gtsam.CustomFactor(noise_model(COV_M), [pose_key, point_key], error)


def _lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, iterations: int) -> None:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


def _is_pose2(values: gtsam.Values, key: int) -> bool:
    try:
        values.atPose2(key)
    except RuntimeError:
        return False
    return True


def _perturbed(values: gtsam.Values, rng: np.random.Generator) -> gtsam.Values:
    out = gtsam.Values()
    for key in values.keys():
        ch = chr(gtsam.Symbol(key).chr())
        if ch == "x":
            out.insert(key, values.atPose2(key).retract(rng.normal(0, 0.01, 3)))
        elif ch == "a" and _is_pose2(values, key):
            a = values.atPose2(key)
            out.insert(key, gtsam.Pose2(a.x(), a.y(), a.theta() + rng.normal(0, 0.02)))
        elif ch == "a":
            out.insert(key, gtsam.Rot2(values.atRot2(key).theta() + rng.normal(0, 0.02)))
        else:
            v = values.atVector(key)
            out.insert(key, v + rng.normal(0, 0.01, v.shape[0]))
    return out


def _time_case(
    name: str,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    args: argparse.Namespace,
    rng: np.random.Generator,
) -> tuple[float, float]:
    lin = _median_time(lambda: graph.linearize(values), args.repeats)
    start = _perturbed(values, rng)
    lm = _median_time(lambda: _lm(graph, start, args.iterations), args.repeats)
    print(
        f"  {name:<44s} factors {graph.size():6d}  linearize {lin * 1e3:9.1f} ms"
        f"  LM({args.iterations} it) {lm * 1e3:9.1f} ms",
        flush=True,
    )
    return lin, lm


def _corner_comparison(
    poses: list[np.ndarray],
    lms: np.ndarray,
    vis: list[np.ndarray],
    args: argparse.Namespace,
    rng: np.random.Generator,
) -> None:
    """Case 4: inverse depth vs Point3 + built-in, LM to convergence from dead reckoning."""
    sigma_m = 0.003  # about 0.6 px at f = 200 px
    prior = HeightPrior()
    cov_m = np.eye(2) * sigma_m**2
    # noisy odometry and dead-reckoning initial poses
    odo_cov = accumulate_odometry(np.full(4, 0.0025), np.full(4, 0.0025), 0.33, 1e-4, 1e-4)[1]
    chol = np.linalg.cholesky(odo_cov)
    deltas, init_poses = [], [gtsam.Pose2(*poses[0])]
    for i in range(1, len(poses)):
        true_d = gtsam.Pose2(*poses[i - 1]).between(gtsam.Pose2(*poses[i]))
        d = true_d.retract(chol @ rng.standard_normal(3))
        deltas.append(d)
        init_poses.append(init_poses[-1].compose(d))
    meas = [
        {int(j): project_point(p, lms[j], OFFSET)[0] + rng.normal(0, sigma_m, 2) for j in v}
        for p, v in zip(poses, vis, strict=True)
    ]

    def build(kind: str) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[int, int]]:
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose2(
                X(0), gtsam.Pose2(*poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)
            )
        )
        for i, d in enumerate(deltas):
            graph.add(
                gtsam.BetweenFactorPose2(
                    X(i), X(i + 1), d, gtsam.noiseModel.Gaussian.Covariance(odo_cov)
                )
            )
        for i, p in enumerate(init_poses):
            values.insert(X(i), p)
        anchor: dict[int, int] = {}
        for i, frame in enumerate(meas):
            idp_obs = []
            p0 = np.array([init_poses[i].x(), init_poses[i].y(), init_poses[i].theta()])
            for j, m in frame.items():
                first = j not in anchor
                if first:
                    anchor[j] = i
                if kind == "idp":
                    if first:
                        graph.add(inverse_depth_first_sight_prior(C(j), m, cov_m, prior))
                        values.insert(C(j), np.array([m[0], m[1], prior.rho_mean]))
                    else:
                        idp_obs.append(InverseDepthObservation(X(anchor[j]), C(j), m, cov_m))
                else:
                    graph.add(projection_factor(X(i), C(j), m, cov_m, OFFSET))
                    if first:
                        pt = init_point_from_observation(p0, m, prior.height_mean, OFFSET)[0]
                        values.insert(C(j), pt)
                        graph.add(height_prior_factor(C(j), pt[:2], OFFSET, prior))
            if idp_obs:
                graph.add(inverse_depth_frame_factor(X(i), idp_obs, OFFSET))
        return graph, values, anchor

    print("4. corners, LM to convergence (noisy odometry and observations, sigma_m 0.003)")
    for kind in ("point3", "idp"):
        graph, values, anchor = build(kind)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        params.setRelativeErrorTol(1e-9)
        t0 = time.perf_counter()
        try:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            result = opt.optimize()
        except RuntimeError as exc:  # CheiralityException from the built-in
            print(f"  {kind:<8s} failed: {exc}")
            continue
        elapsed = time.perf_counter() - t0
        pos_err = [
            np.hypot(result.atPose2(X(i)).x() - p[0], result.atPose2(X(i)).y() - p[1])
            for i, p in enumerate(poses)
        ]
        c_err, h_err = [], []
        for j, a in anchor.items():
            if kind == "idp":
                ap = result.atPose2(X(a))
                pt = inverse_depth_to_point(
                    np.array([ap.x(), ap.y(), ap.theta()]), result.atVector(C(j)), OFFSET
                )[0]
            else:
                pt = result.atPoint3(C(j))
            c_err.append(np.linalg.norm(pt - lms[j]))
            h_err.append(pt[2] - lms[j][2])
        dr_err = [
            np.hypot(q.x() - p[0], q.y() - p[1]) for q, p in zip(init_poses, poses, strict=True)
        ]
        print(
            f"  {kind:<8s} LM {elapsed * 1e3:8.0f} ms, {opt.iterations():2d} it; pose RMS "
            f"{np.sqrt(np.mean(np.square(pos_err))) * 100:.2f} cm (dead reckoning "
            f"{np.sqrt(np.mean(np.square(dr_err))) * 100:.1f} cm); corner RMS "
            f"{np.sqrt(np.mean(np.square(c_err))) * 100:.2f} cm, height RMS "
            f"{np.sqrt(np.mean(np.square(h_err))) * 100:.2f} cm (median |.| "
            f"{np.median(np.abs(h_err)) * 100:.2f} cm, max {np.max(np.abs(h_err)) * 100:.0f} cm)",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=2000)
    parser.add_argument("--per-pose", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", default="projection,idp,axis,corners")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    poses, lms = _world(args.poses, rng)
    vis = [_visible(p, lms, args.per_pose) for p in poses]
    n_obs = sum(len(v) for v in vis)
    print(
        f"{args.poses} poses, {len(lms)} landmarks, {n_obs} observations, "
        f"median of {args.repeats} (machine shared: absolute times inflated)"
    )

    base = gtsam.Values()
    for i, p in enumerate(poses):
        base.insert(X(i), gtsam.Pose2(*p))
    cases = args.cases.split(",")

    if "projection" in cases:
        print("1. position observations (Point3 landmarks)")
        values = gtsam.Values(base)
        for j, lm in enumerate(lms):
            values.insert(L(j), lm)
        g_builtin, g_custom = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        _odometry(g_builtin, poses)
        _odometry(g_custom, poses)
        for i, p in enumerate(poses):
            for j in vis[i]:
                m = project_point(p, lms[j], OFFSET)[0]
                g_builtin.add(projection_factor(X(i), L(int(j)), m, COV_M, OFFSET))
                g_custom.add(_custom_projection(X(i), L(int(j)), m))
        ref = _time_case("built-in PlanarProjectionFactor2 (ref)", g_builtin, values, args, rng)
        cus = _time_case("CustomFactor(project_point) per observation", g_custom, values, args, rng)
        print(
            f"  ratio custom/built-in: linearize {cus[0] / ref[0]:.1f}x, LM {cus[1] / ref[1]:.1f}x"
        )

    if "idp" in cases:
        print("2. inverse-depth corners (CustomFactor)")
        values = gtsam.Values(base)
        g_obs, g_frame = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        _odometry(g_obs, poses)
        _odometry(g_frame, poses)
        anchor: dict[int, int] = {}
        for i, p in enumerate(poses):
            frame_obs: list[InverseDepthObservation] = []
            for j in (int(v) for v in vis[i]):
                m = project_point(p, lms[j], OFFSET)[0]
                if j not in anchor:
                    anchor[j] = i
                    idp = np.array([m[0], m[1], 1.0 / (lms[j][2] - OFFSET[2])])
                    values.insert(C(j), idp)
                    prior = inverse_depth_first_sight_prior(C(j), m, COV_M)
                    g_obs.add(prior)
                    g_frame.add(prior)
                    continue
                m = project_inverse_depth(p, poses[anchor[j]], values.atVector(C(j)), OFFSET)[0]
                g_obs.add(inverse_depth_factor(X(i), X(anchor[j]), C(j), m, COV_M, OFFSET))
                frame_obs.append(InverseDepthObservation(X(anchor[j]), C(j), m, COV_M))
            if frame_obs:
                g_frame.add(inverse_depth_frame_factor(X(i), frame_obs, OFFSET))
        ref = _time_case("one CustomFactor per observation (ref)", g_obs, values, args, rng)
        fr = _time_case("one CustomFactor per frame", g_frame, values, args, rng)
        print(
            f"  ratio per-frame/per-observation: linearize {fr[0] / ref[0]:.2f}x, "
            f"LM {fr[1] / ref[1]:.2f}x"
        )

    if "axis" in cases:
        print("3. lamp axes, every observed landmark oriented")
        values = gtsam.Values(base)
        phis = rng.uniform(-np.pi / 2, np.pi / 2, len(lms))
        for j, phi in enumerate(phis):
            values.insert(A(j), gtsam.Rot2(phi))
        g_obs, g_frame = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        _odometry(g_obs, poses)
        _odometry(g_frame, poses)
        for i, p in enumerate(poses):
            frame_axis: list[AxisObservation] = []
            for j in (int(v) for v in vis[i]):
                alpha = phis[j] - p[2]
                g_obs.add(lamp_axis_factor(X(i), A(j), alpha, 0.02))
                frame_axis.append(AxisObservation(A(j), alpha, 0.02))
            g_frame.add(lamp_axis_frame_factor(X(i), frame_axis))
        values_p = gtsam.Values(base)  # A(j) as a Pose2 for the built-in form
        g_between = gtsam.NonlinearFactorGraph()
        _odometry(g_between, poses)
        for j, phi in enumerate(phis):
            values_p.insert(A(j), gtsam.Pose2(float(lms[j][0]), float(lms[j][1]), float(phi)))
            g_between.add(axis_anchor_prior(A(j), lms[j][:2], float(phi)))
        for i, p in enumerate(poses):
            for j in (int(v) for v in vis[i]):
                alpha = phis[j] - p[2]
                g_between.add(lamp_axis_between_factor(X(i), A(j), alpha, 0.02, alpha))
        ref = _time_case("one CustomFactor per observation (ref)", g_obs, values, args, rng)
        fr = _time_case("one CustomFactor per frame", g_frame, values, args, rng)
        bt = _time_case("built-in BetweenFactorPose2 per observation", g_between, values_p,
                        args, rng)
        print(
            f"  ratio per-frame/per-observation: linearize {fr[0] / ref[0]:.2f}x, "
            f"LM {fr[1] / ref[1]:.2f}x; built-in/per-observation: linearize "
            f"{bt[0] / ref[0]:.2f}x, LM {bt[1] / ref[1]:.3f}x"
        )

    if "corners" in cases:
        _corner_comparison(poses, lms, vis, args, rng)


if __name__ == "__main__":
    main()
