"""Joint solve of four cameras on chessboard corners: every camera's intrinsics and distortion,
the poses of CCDs 2–4 relative to CCD 1 and one board pose per view, refined together by
Levenberg–Marquardt on all corner reprojection errors, with per-corner outlier rejection and
the covariance of every parameter.

Why joint: calibrating each camera alone and then fitting the stereo poses with the
intrinsics held fixed leaves the intrinsics' errors in the poses (0.24–0.28° on a real stereo
rig, 6σ by mrcal's uncertainty). Why per corner: one bad corner (a glint, a smudge) used to
cost its whole view; here it is rejected alone, and a view whose corners disagree as a whole
(an out-of-sync pair) is dropped for that CCD and named.

Camera model: OpenCV's five-coefficient model (k1, k2, p1, p2, k3). Poses: X_k = R_k·X_1 + T_k
(mm), R from a Rodrigues vector; board points X_1 = R_v·P + t_v."""

from __future__ import annotations

import dataclasses
import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np

import cohflash_jax  # noqa: F401  (turns float64 on: the solve needs it)

INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
N_INTRINSICS = len(INTRINSICS)
# A corner is an outlier beyond this many σ (σ of one coordinate): the 2-D error's squared
# norm over σ² is χ² with 2 degrees of freedom, and P(χ²₂ > 5²) = 4·10⁻⁶, under one false
# rejection in 10⁵ corners
OUTLIER_SIGMAS = 5.0
# A camera's view is dropped as a whole where more than this fraction of its corners are outliers
VIEW_OUTLIER_FRACTION = 0.5
MAX_ROUNDS = 12


def rodrigues(r):
    """Rotation matrix of a Rodrigues vector; smooth at zero (a series below 1e-4 rad)."""
    theta2 = r @ r
    small = theta2 < 1e-8
    t2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(t2)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / t2)
    k = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return jnp.eye(3) + a * k + b * (k @ k)


def project(intrinsics, points):
    """OpenCV projection of camera-frame points (..., 3) → pixels (..., 2)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics
    x, y = points[..., 0] / points[..., 2], points[..., 1] / points[..., 2]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return jnp.stack([fx * xd + cx, fy * yd + cy], axis=-1)


def unproject(intrinsics, pixels, iterations: int = 30):
    """Normalised coordinates (x, y) of distorted pixels, by OpenCV's fixed-point iteration
    (differentiable; converged to < 1e-10 for the distortions of real lenses)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics
    xd, yd = (pixels[..., 0] - cx) / fx, (pixels[..., 1] - cy) / fy

    def step(_, xy):
        x, y = xy
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return (xd - dx) / radial, (yd - dy) / radial

    x, y = jax.lax.fori_loop(0, iterations, step, (xd, yd))
    return jnp.stack([x, y], axis=-1)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where each block lives in the flat parameter vector."""

    cameras: int
    views: int

    @property
    def size(self) -> int:
        return self.cameras * N_INTRINSICS + (self.cameras - 1) * 6 + self.views * 6

    def intrinsics(self, c: int) -> slice:
        return slice(c * N_INTRINSICS, (c + 1) * N_INTRINSICS)

    def camera_pose(self, c: int) -> slice:
        """(rvec, T) of camera c ≥ 1 relative to camera 0."""
        start = self.cameras * N_INTRINSICS + (c - 1) * 6
        return slice(start, start + 6)

    def board_pose(self, v: int) -> slice:
        start = self.cameras * N_INTRINSICS + (self.cameras - 1) * 6 + v * 6
        return slice(start, start + 6)


def corner_predictions(params, layout: Layout, object_points):
    """Predicted pixels (cameras, views, corners, 2) of every board corner."""
    boards = params[layout.board_pose(0).start :].reshape(layout.views, 6)
    rot = jax.vmap(rodrigues)(boards[:, :3])
    world = jnp.einsum("vij,nj->vni", rot, object_points) + boards[:, None, 3:]  # CCD 1 frame
    out = []
    for c in range(layout.cameras):
        pts = world
        if c > 0:
            pose = params[layout.camera_pose(c)]
            pts = jnp.einsum("ij,vnj->vni", rodrigues(pose[:3]), world) + pose[3:]
        out.append(project(params[layout.intrinsics(c)], pts))
    return jnp.stack(out)


@dataclasses.dataclass
class JointSolution:
    """The joint solve's parameters, their covariance, and which corners it kept."""

    params: np.ndarray
    covariance: np.ndarray
    layout: Layout
    inliers: np.ndarray  # (cameras, views, corners) bool
    residuals_px: np.ndarray  # (cameras, views, corners, 2), NaN where not observed
    sigma_px: float  # corner noise (one coordinate), from the inliers
    rms_px: float
    dropped_views: dict  # (camera, view index) → reason

    def intrinsics(self, c: int) -> np.ndarray:
        return self.params[self.layout.intrinsics(c)]

    def camera_matrix(self, c: int) -> np.ndarray:
        fx, fy, cx, cy = self.intrinsics(c)[:4]
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    def dist_coeffs(self, c: int) -> np.ndarray:
        return np.asarray(self.intrinsics(c)[4:])

    def pose(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) of camera c ≥ 1: X_c = R·X_1 + T (mm)."""
        p = self.params[self.layout.camera_pose(c)]
        return cv2.Rodrigues(p[:3].copy())[0], p[3:].copy()

    def board_pose(self, v: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of view v's board in CCD 1's frame: X_1 = R·P + t (mm)."""
        p = self.params[self.layout.board_pose(v)]
        return cv2.Rodrigues(p[:3].copy())[0], p[3:].copy()

    def pose_covariance(self, c: int) -> np.ndarray:
        s = self.layout.camera_pose(c)
        return self.covariance[s, s]

    def intrinsics_sigma(self, c: int) -> np.ndarray:
        s = self.layout.intrinsics(c)
        return np.sqrt(np.diag(self.covariance[s, s]))


def rms_px(errors) -> float:
    """RMS length (px) of 2-D reprojection errors (..., 2)."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(errors) ** 2, axis=-1))))


def levenberg_marquardt(normal_equations, trial_cost, x0, max_iter: int = 200, tol: float = 1e-12):
    """Minimise |r(x)|² from x0 with Marquardt's diagonal scaling; returns x.
    `normal_equations(x)` → (JᵀJ, Jᵀr, |r|²); `trial_cost(x, JᵀJ, Jᵀr, λ)` → (step, |r(x + step)|²)."""
    x = jnp.asarray(x0, jnp.float64)
    lam = 1e-3
    jtj, g, cost = normal_equations(x)
    cost = float(cost)
    for _ in range(max_iter):
        improved, done = False, False
        for _ in range(20):
            step, cost_new = trial_cost(x, jtj, g, lam)
            cost_new = float(cost_new)
            if np.isfinite(cost_new) and cost_new < cost:
                x, improved = x + step, True
                lam = max(lam / 3, 1e-12)
                done = cost - cost_new < tol * max(cost, 1e-30)
                cost = cost_new
                break
            lam *= 10
        if not improved or done:
            break
        jtj, g, _ = normal_equations(x)
    return np.asarray(x)


def weighted_residuals(params, layout: Layout, object_points, observed, weight):
    """(predicted − observed) × weight, flattened: the solve's residual vector (px)."""
    return ((corner_predictions(params, layout, object_points) - observed) * weight[..., None]).ravel()


@functools.partial(jax.jit, static_argnums=1)
def predict(params, layout: Layout, object_points):
    return corner_predictions(params, layout, object_points)


@functools.partial(jax.jit, static_argnums=1)
def normal_equations(params, layout: Layout, object_points, observed, weight, blank):
    """(JᵀJ, Jᵀr, |r|²) of the weighted residuals at `params`, JᵀJ with 1 added on the diagonal
    where `blank` is 1 (the parameters of blank views, which no residual sees: `solve`)."""
    r = weighted_residuals(params, layout, object_points, observed, weight)
    jac = jax.jacfwd(weighted_residuals)(params, layout, object_points, observed, weight)
    return jac.T @ jac + jnp.diag(blank), jac.T @ r, r @ r


@functools.partial(jax.jit, static_argnums=4)
def trial_cost(params, jtj, g, lam, layout: Layout, object_points, observed, weight):
    """The Marquardt step for damping λ and the cost |r|² after it (inf where the step fails)."""
    scale = jnp.maximum(jnp.diag(jtj), 1e-12)
    step = -jnp.linalg.solve(jtj + lam * jnp.diag(scale), g)
    r = weighted_residuals(params + step, layout, object_points, observed, weight)
    return step, jnp.where(jnp.all(jnp.isfinite(step)), r @ r, jnp.inf)


# The solve's programs hold the views in multiples of this many: they are compiled for a
# number of views, and a rig recalibrated with a few views more or fewer runs the programs
# compiled already. The views beyond the rig's are blank (no corner seen)
VIEW_BUCKET = 8


def solve(initial: np.ndarray, layout: Layout, object_points: np.ndarray, observed: np.ndarray, seen: np.ndarray):
    """Joint solve from `initial` on `observed` corners (cameras, views, corners, 2) where
    `seen` (cameras, views, corners) is True; rejects outlier corners and views, re-solving
    until the inlier set is stable, and states the covariance σ²·(JᵀJ)⁻¹ over the inliers.

    The views are padded to a multiple of `VIEW_BUCKET` with blank ones, each posed as the
    first view: no residual sees a blank view's pose, so its block of JᵀJ is set to the
    identity (its Marquardt step is then 0, exactly) and it is cut from the solution; the
    rig's own block of JᵀJ, its steps and its covariance are those of the unpadded solve."""
    padded = Layout(layout.cameras, -(-layout.views // VIEW_BUCKET) * VIEW_BUCKET)
    extra = padded.views - layout.views
    obj = jnp.asarray(object_points, jnp.float64)
    obs = jnp.asarray(np.pad(np.nan_to_num(observed), ((0, 0), (0, extra), (0, 0), (0, 0))), jnp.float64)
    blank = jnp.asarray(np.arange(padded.size) >= layout.size, jnp.float64)
    inliers = seen.copy()
    dropped = {}
    initial = np.asarray(initial, np.float64)
    x = np.concatenate([initial, np.tile(initial[layout.board_pose(0)], extra)])
    weights = lambda inliers: jnp.asarray(np.pad(inliers, ((0, 0), (0, extra), (0, 0))), jnp.float64)

    def fitted(x, inliers):
        """Levenberg–Marquardt on the inliers from x (padded): (x, errors of every corner (…, 2))."""
        w = weights(inliers)
        x = levenberg_marquardt(
            lambda p: normal_equations(p, padded, obj, obs, w, blank),
            lambda p, a, b, lam: trial_cost(p, a, b, lam, padded, obj, obs, w),
            x,
        )
        predicted = np.asarray(predict(jnp.asarray(x), padded, obj))[:, : layout.views]
        return x, predicted - np.asarray(observed)

    for _ in range(MAX_ROUNDS):
        x, err = fitted(x, inliers)
        norm = np.linalg.norm(err, axis=-1)
        # σ of one coordinate from the inliers' median error norm (Rayleigh: median = 1.1774σ)
        sigma = float(np.median(norm[inliers]) / 1.1774)
        new = seen & (norm < OUTLIER_SIGMAS * sigma)
        for c, v in dropped:
            new[c, v] = False
        # a camera's view whose corners disagree as a whole is dropped, the worst one per round:
        # until it is gone, it pulls the board pose and so the other cameras' views of it too
        worst, worst_err = None, 0.0
        for c, v in zip(*np.nonzero(seen.any(axis=2))):
            if (c, v) in dropped:
                continue
            bad = 1 - new[c, v][seen[c, v]].mean()
            err_cv = float(np.median(norm[c, v][seen[c, v]]))
            if bad > VIEW_OUTLIER_FRACTION and err_cv > worst_err:
                worst, worst_err = (int(c), int(v)), err_cv
                reason = (
                    f"{bad:.0%} of its corners disagree with the other CCDs' view of the board "
                    f"(median error {err_cv:.1f} px): out of sync, or another board?"
                )
        if worst is not None:
            dropped[worst] = reason
            new[worst] = False
        if np.array_equal(new, inliers):
            break
        inliers = new
    else:  # the rounds ran out on a changed inlier set: fit it before stating anything of it
        x, err = fitted(x, inliers)
    jtj, _, cost = normal_equations(jnp.asarray(x), padded, obj, obs, weights(inliers), blank)
    dof = max(int(inliers.sum()) * 2 - layout.size, 1)
    sigma2 = float(cost) / dof
    n = layout.size  # the rig's own parameters: the blank views' block is uncoupled from them
    cov = sigma2 * np.linalg.pinv(np.asarray(jtj)[:n, :n])
    err = np.where(seen[..., None], err, np.nan)
    rms = rms_px(err[inliers])
    return JointSolution(np.asarray(x)[:n], cov, layout, inliers, err, float(np.sqrt(sigma2)), rms, dropped)


def pixel_map(intrinsics_ref, pose, intrinsics_cam, pixels, distance_mm, mirrored_width):
    """Pixels (P, 2) of CCD 1 → pixels (P, 2) of a camera at `pose` (rvec, T relative to CCD 1)
    with `intrinsics_cam`, seeing the same point of a fronto-parallel plane at `distance_mm`.
    `mirrored_width` > 0 un-flips a mirrored CCD's frame of that width (0: not mirrored). Every
    number is an argument, so one compiled program serves every camera, distance and flip."""
    xy = unproject(intrinsics_ref, pixels)
    pts = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1) * distance_mm
    pts = pts @ rodrigues(pose[:3]).T + pose[3:]
    uv = project(intrinsics_cam, pts)
    u = jnp.where(mirrored_width > 0, mirrored_width - 1 - uv[..., 0], uv[..., 0])
    return uv.at[..., 0].set(u)


def map_function(layout: Layout, camera: int, distance_mm: float, mirrored_width: int | None):
    """(params, pixels (P, 2) of CCD 1) → pixels (P, 2) of `camera` (`pixel_map` of the joint
    parameter vector); `mirrored_width` un-flips a mirrored CCD's frame."""

    def fn(params, pixels):
        return pixel_map(
            params[layout.intrinsics(0)],
            params[layout.camera_pose(camera)],
            params[layout.intrinsics(camera)],
            pixels,
            distance_mm,
            mirrored_width or 0,
        )

    return fn


# the map's Jacobian in its three blocks (CCD 1's intrinsics, the camera's pose, its
# intrinsics): one program per pixel count, not one per camera, distance and call
map_jacobian = jax.jit(jax.jacfwd(pixel_map, argnums=(0, 1, 2)))


def map_sigma_at(solution: JointSolution, camera: int, pixels, image_width: int, distance_mm: float, mirrored: bool):
    """1σ (px) of the pixel map at CCD 1 `pixels` (P, 2): the larger axis of the map's 2×2
    covariance, propagated from the joint covariance (board poses marginalised: the map
    depends on none of them, so only the covariance of its 24 parameters enters)."""
    layout = solution.layout
    blocks = (layout.intrinsics(0), layout.camera_pose(camera), layout.intrinsics(camera))
    columns = np.concatenate([np.arange(b.start, b.stop) for b in blocks])
    params = np.asarray(solution.params, np.float64)
    jac = map_jacobian(
        *(jnp.asarray(params[b]) for b in blocks),
        jnp.asarray(pixels, jnp.float64),
        jnp.float64(distance_mm),
        jnp.float64(image_width if mirrored else 0),
    )
    jac = np.concatenate([np.asarray(j) for j in jac], axis=-1)  # (P, 2, 24)
    cov = np.einsum("pin,nm,pjm->pij", jac, solution.covariance[np.ix_(columns, columns)], jac)
    return np.sqrt(np.linalg.eigvalsh(cov)[:, -1].clip(0))


def map_sigma_px(
    solution: JointSolution, camera: int, image_size, distance_mm: float, mirrored: bool, grid=(32, 24)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map's 1σ on a grid × grid of CCD 1 pixels: (u (gx,), v (gy,), σ (gy, gx)). It grows
    fast outside the part of the image the board covered, where the model is extrapolated."""
    w, h = image_size
    u = np.linspace(0, w - 1, grid[0])
    v = np.linspace(0, h - 1, grid[1])
    pix = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    sigma = map_sigma_at(solution, camera, pix, w, distance_mm, mirrored)
    return u, v, sigma.reshape(grid[1], grid[0])
