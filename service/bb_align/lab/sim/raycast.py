"""Vectorised ray casting of one rotating-LiDAR sweep, with self-motion distortion.

The scene is extruded footprints over a flat ground (see ``world``), so a ray is cast in two steps:
1. per azimuth column, the horizontal ray against every footprint (slab test for rectangles, quadratic for
   circles) gives the entry/exit distances of the K nearest footprints it crosses;
2. per beam, the ray's height z(d) = z0 + d tan(elevation) selects the first footprint whose [zb, zt] it
   meets between entry and exit (walls, roofs seen from above, crowns seen from below), else the ground.

Self-motion distortion: column c fires at t_c (the sweep starts and ends facing backwards, faces forward at
mid-sweep t_mid, spinning clockwise seen from above, like Velodyne sensors); the car, and every other moving
car, is where it is at t_c. The points are reported in the sensor frame of their own firing time with no
de-skewing, while the frame's pose ``T_world_sensor`` is the one at t_mid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bb_align.engine.geometry import rotation_rpy

from .sensors import SensorModel
from .world import ShapeArrays, World

K_NEAREST = 12  # footprints kept per azimuth column (nearer ones occlude the rest for almost every beam)
GROUND_REFLECTIVITY = 0.25  # asphalt, kerb stone and verge at 905 nm, between pavement's ~0.1 and grass' ~0.4


@dataclass(frozen=True)
class Mount:
    """Where the LiDAR sits on its car: forward offset and height of the optical centre above the ground,
    and a small residual tilt (mounting error plus body pitch/roll), radians."""

    height_m: float = 1.9
    x_offset_m: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0


@dataclass
class Sweep:
    points: np.ndarray  # (N, 4) float32: x, y, z, intensity in the sensor frame (distorted, as measured)
    owner: np.ndarray  # (N,) vehicle index hit, -1 static scene, -2 ground
    time: np.ndarray  # (N,) firing time of each point, seconds
    T_world_sensor: np.ndarray  # 4x4 at t_mid


def sensor_pose(world: World, vehicle: int, mount: Mount, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World (x, y, yaw) of the sensor at times t."""
    x, y, yaw = world.vehicles[vehicle].pose(t)
    return x + np.cos(yaw) * mount.x_offset_m, y + np.sin(yaw) * mount.x_offset_m, yaw


def sensor_twist(world: World, vehicle: int, mount: Mount, t: float, h_s: float = 1e-3) -> tuple[float, float, float]:
    """(vx, vy) of the sensor in its own frame at time t, m/s, and its yaw rate, rad/s (central differences over
    +-h_s): what the car's odometry tells a sender that de-skews its sweep (bb_align_client.deskew_sweep)."""
    x, y, a = (np.ravel(v) for v in sensor_pose(world, vehicle, mount, np.array([t - h_s, t + h_s])))
    am = 0.5 * (a[0] + a[1])
    vx_w, vy_w = (x[1] - x[0]) / (2 * h_s), (y[1] - y[0]) / (2 * h_s)
    vx = np.cos(am) * vx_w + np.sin(am) * vy_w
    vy = -np.sin(am) * vx_w + np.cos(am) * vy_w
    return float(vx), float(vy), float(np.arctan2(np.sin(a[1] - a[0]), np.cos(a[1] - a[0])) / (2 * h_s))


def T_world_sensor_at(world: World, vehicle: int, mount: Mount, t: float) -> np.ndarray:
    x, y, yaw = (float(v) for v in sensor_pose(world, vehicle, mount, t))
    T = np.eye(4)
    T[:3, :3] = rotation_rpy(mount.roll, mount.pitch, yaw)
    T[:3, 3] = (x, y, mount.height_m)
    return T


def _footprint_hits(ox, oy, dx, dy, shapes: ShapeArrays, vel: np.ndarray | None, dt: np.ndarray, sectors: int = 32):
    """``_footprint_hits_dense``'s arrays, computed per sector of ``sectors`` runs of columns for only the footprints
    whose bounding circle (grown by how far the sensor and the footprint move within the sweep) reaches into the
    sector; a footprint left out could not have been hit, so the arrays are the dense ones wherever a ray meets a
    footprint, and the sweep the same to the bit (tested)."""
    n, m = len(ox), len(shapes)
    t_in, t_out, cos_in = np.full((n, m), np.inf), np.full((n, m), -np.inf), np.ones((n, m))
    if m == 0 or n == 0:
        return t_in, t_out, cos_in
    x0, y0 = float(ox[n // 2]), float(oy[n // 2])
    moved = float(np.hypot(ox - x0, oy - y0).max())
    if vel is not None and len(vel):
        moved += float(np.hypot(vel[:, 0], vel[:, 1]).max() * np.abs(dt).max())
    rel = shapes.xy - (x0, y0)
    dist = np.hypot(rel[:, 0], rel[:, 1])
    reach = shapes.radius + moved + 1e-6
    half = np.where(dist > reach, np.arcsin(np.clip(reach / np.maximum(dist, 1e-9), 0.0, 1.0)), np.pi)
    bearing = np.arctan2(rel[:, 1], rel[:, 0])
    phi = np.arctan2(dy, dx)
    for cols in np.array_split(np.arange(n), min(sectors, n)):
        centre = float(np.arctan2(dy[cols].sum(), dx[cols].sum()))
        span = float(np.abs(np.angle(np.exp(1j * (phi[cols] - centre)))).max())
        sel = np.flatnonzero(np.abs(np.angle(np.exp(1j * (bearing - centre)))) <= half + span + 1e-9)
        if len(sel):
            part = _footprint_hits_dense(
                ox[cols], oy[cols], dx[cols], dy[cols], shapes.take(sel), None if vel is None else vel[sel], dt[cols]
            )
            for full, sub in zip((t_in, t_out, cos_in), part, strict=True):
                full[np.ix_(cols, sel)] = sub
    return t_in, t_out, cos_in


def _footprint_hits_dense(ox, oy, dx, dy, shapes: ShapeArrays, vel: np.ndarray | None, dt: np.ndarray):
    """Entry/exit distances (n_cols, M) of horizontal rays (origin o, unit direction d per column), and the cosine
    between each ray and the normal of the side face it enters by (1 for a ray that starts inside)."""
    cx = shapes.xy[None, :, 0]
    cy = shapes.xy[None, :, 1]
    if vel is not None:
        cx = cx + vel[None, :, 0] * dt[:, None]
        cy = cy + vel[None, :, 1] * dt[:, None]
    rx, ry = ox[:, None] - cx, oy[:, None] - cy
    t_in = np.full(rx.shape, np.inf)
    t_out = np.full(rx.shape, -np.inf)
    cos_in = np.ones(rx.shape)
    p = ~shapes.is_cyl
    if p.any():
        c, s = np.cos(shapes.yaw[p]), np.sin(shapes.yaw[p])
        lx = c * rx[:, p] + s * ry[:, p]
        ly = -s * rx[:, p] + c * ry[:, p]
        ldx = c * dx[:, None] + s * dy[:, None]
        ldy = -s * dx[:, None] + c * dy[:, None]
        ldx = np.where(np.abs(ldx) < 1e-12, 1e-12, ldx)
        ldy = np.where(np.abs(ldy) < 1e-12, 1e-12, ldy)
        a, b = shapes.a[p], shapes.b[p]
        t1, t2 = (-a - lx) / ldx, (a - lx) / ldx
        t3, t4 = (-b - ly) / ldy, (b - ly) / ldy
        tx, ty = np.minimum(t1, t2), np.minimum(t3, t4)
        t_in[:, p] = np.maximum(tx, ty)
        t_out[:, p] = np.minimum(np.maximum(t1, t2), np.maximum(t3, t4))
        cos_in[:, p] = np.where(tx > ty, np.abs(ldx), np.abs(ldy))  # entered through an x face or a y face
    q = shapes.is_cyl
    if q.any():
        bq = rx[:, q] * dx[:, None] + ry[:, q] * dy[:, None]
        cq = rx[:, q] ** 2 + ry[:, q] ** 2 - shapes.a[q] ** 2
        disc = bq * bq - cq
        sq = np.sqrt(np.maximum(disc, 0.0))
        t_in[:, q] = np.where(disc > 0, -bq - sq, np.inf)
        t_out[:, q] = np.where(disc > 0, -bq + sq, -np.inf)
        # at the entry point the radial normal n = (r + t d) / a, and n . d = bq + t_in = -sq
        cos_in[:, q] = np.clip(sq / shapes.a[q], 0.0, 1.0)
    hit = t_out > np.maximum(t_in, 0.0)
    cos_in = np.where(t_in > 0.0, cos_in, 1.0)
    return np.where(hit, np.maximum(t_in, 0.0), np.inf), t_out, cos_in


def _ground_hits(
    world: World,
    ox,
    oy,
    dx,
    dy,
    z0: float,
    slope: np.ndarray,
    max_range: float,
    rng,
    step: float = 1.0,
    chunk: int = 16,
) -> np.ndarray:
    """Horizontal distance (n_cols, n_beams) at which each beam meets the terrain (or its grass), inf if not.

    The terrain profile under each column's ray is sampled once; each downward beam takes the first sample
    where it has gone below the profile, refined linearly between samples."""
    n, n_beams = slope.shape
    ds = np.arange(step, max_range + step, step, dtype=np.float32)
    xy = np.stack([ox[:, None] + dx[:, None] * ds, oy[:, None] + dy[:, None] * ds], axis=-1)
    prof = world.terrain.height_at(xy).astype(np.float32)  # (n, S)
    grass = world.terrain.grass_at(xy).astype(np.float32)
    out = np.full((n, n_beams), np.inf)
    down = np.flatnonzero(slope.min(axis=0) < -1e-6)
    rows = np.arange(n)[:, None]
    for c0 in range(0, len(down), chunk):
        b = down[c0 : c0 + chunk]
        sl = slope[:, b].astype(np.float32)  # (n, nb)
        diff = (z0 + sl[:, :, None] * ds) - prof[:, None, :]  # (n, nb, S) ray height above ground
        below = diff <= 0
        k = np.argmax(below, axis=2)
        found = below.any(axis=2)
        km = np.maximum(k - 1, 0)
        d_hi = np.take_along_axis(diff, km[..., None], 2)[..., 0]
        d_lo = np.take_along_axis(diff, k[..., None], 2)[..., 0]
        frac = np.where(k > 0, d_hi / np.maximum(d_hi - d_lo, 1e-6), 0.0)
        d = np.where(k > 0, ds[km] + frac * step, z0 / np.maximum(-sl, 1e-6))
        lift = rng.random(d.shape) * grass[rows, k]  # grass tops catch the ray a little earlier
        d = d - np.minimum(lift / np.maximum(-sl, 1e-6), 2.0)
        out[:, b] = np.where(found & (sl < -1e-6), d, np.inf)
    return out


def cast_sweep(
    world: World,
    vehicle: int,
    sensor: SensorModel,
    mount: Mount,
    t_mid: float,
    rng: np.random.Generator,
    beam_error_deg: np.ndarray | None = None,
    distortion: bool = True,
) -> Sweep:
    """One full revolution of ``sensor`` on car ``vehicle`` centred on time ``t_mid``.

    ``distortion=False`` freezes the world at t_mid for the whole sweep (an ideal, de-skewed scan). The lasers fire
    at ``sensor.azimuth_phases`` distinct azimuths per column step (``SensorModel.beam_phases``): each phase's beams
    are cast as one set of columns.
    """
    elev = np.asarray(sensor.elevations_deg, dtype=float)
    err = np.zeros_like(elev) if beam_error_deg is None else np.asarray(beam_error_deg, dtype=float)
    phases = sensor.beam_phases()
    vehicles = world.vehicle_shapes(t_mid, exclude={vehicle})  # every phase sees the cars where they are at t_mid
    parts = [
        _cast_columns(
            world, vehicle, vehicles, sensor, mount, t_mid, rng, elev[phases == ph], err[phases == ph], ph, distortion
        )
        for ph in np.unique(phases)
    ]
    t = np.concatenate([p[2] for p in parts])
    order = np.argsort(t, kind="stable")  # firing order, as the sensor streams them
    return Sweep(
        np.concatenate([p[0] for p in parts])[order],
        np.concatenate([p[1] for p in parts])[order],
        t[order],
        T_world_sensor_at(world, vehicle, mount, t_mid),
    )


def _cast_columns(
    world: World,
    vehicle: int,
    vehicles: tuple[ShapeArrays, np.ndarray],
    sensor: SensorModel,
    mount: Mount,
    t_mid: float,
    rng: np.random.Generator,
    elev_deg: np.ndarray,
    err_deg: np.ndarray,
    phase: float,
    distortion: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, owners and firing times of the beams ``elev_deg`` (calibration errors ``err_deg``) firing ``phase``
    column steps into each column; ``vehicles``: the other cars' prisms and velocities at t_mid."""
    n = sensor.columns
    period = 1.0 / sensor.spin_hz if distortion else 0.0
    frac = (np.arange(n) + phase) / n
    t_col = t_mid + (frac - 0.5) * period
    az = np.pi - 2 * np.pi * frac  # sensor-frame azimuth of each column (clockwise spin)
    ox, oy, yaw = sensor_pose(world, vehicle, mount, t_col)
    phi = yaw + az
    dx, dy = np.cos(phi), np.sin(phi)
    dt = t_col - t_mid

    # Candidate footprints near the sensor.
    reach = sensor.max_range_m + 2.0
    x0, y0 = float(ox[n // 2]), float(oy[n // 2])
    st = world.static
    near = np.hypot(st.xy[:, 0] - x0, st.xy[:, 1] - y0) < reach + st.radius
    veh, vel = vehicles
    vnear = np.hypot(veh.xy[:, 0] - x0, veh.xy[:, 1] - y0) < reach + veh.radius + 5.0
    st, veh, vel = st.take(near), veh.take(vnear), vel[vnear]
    tin_s, tout_s, cos_s = _footprint_hits(ox, oy, dx, dy, st, None, dt)
    tin_v, tout_v, cos_v = _footprint_hits(ox, oy, dx, dy, veh, vel, dt)
    shapes = ShapeArrays.concat([st, veh])
    t_in = np.concatenate([tin_s, tin_v], axis=1)
    t_out = np.concatenate([tout_s, tout_v], axis=1)
    cos_side = np.concatenate([cos_s, cos_v], axis=1)

    # K nearest crossed footprints per column.
    k = min(K_NEAREST, t_in.shape[1])
    rows = np.arange(n)[:, None]
    if k > 0:
        idx = np.argpartition(t_in, k - 1, axis=1)[:, :k] if t_in.shape[1] > k else np.tile(np.arange(k), (n, 1))
        kin, kout, kcos = t_in[rows, idx], t_out[rows, idx], cos_side[rows, idx]
        zb, zt = shapes.zb[idx], shapes.zt[idx]
        por, refl, own = shapes.porosity[idx], shapes.reflect[idx], shapes.owner[idx]
        relief = shapes.relief[idx]
    else:
        kin = kout = kcos = zb = zt = por = refl = relief = np.zeros((n, 0))
        own = np.zeros((n, 0), dtype=np.int64)

    # Beam geometry (true directions include calibration error and the residual tilt).
    elev = np.radians(elev_deg)
    err = np.radians(err_deg)
    e_true = elev[None, :] + err[None, :] - mount.pitch * np.cos(az)[:, None] + mount.roll * np.sin(az)[:, None]
    slope = np.tan(e_true)  # (n, B)
    z0 = mount.height_m + float(world.terrain.height_at(np.array([x0, y0])))

    sl = slope[:, :, None]
    sl = np.where(np.abs(sl) < 1e-9, 1e-9, sl)
    da = (zb[:, None, :] - z0) / sl
    db = (zt[:, None, :] - z0) / sl
    lo, hi = np.minimum(da, db), np.maximum(da, db)
    enter = np.maximum(kin[:, None, :], lo)
    leave = np.minimum(kout[:, None, :], hi)
    hit = enter <= leave
    # cosine of incidence: a side face (its horizontal cosine times the beam's cos(elevation)) or, for a ray that
    # comes in through the top or bottom (a roof seen from above, a crown from below), the horizontal plane
    cos_e = 1.0 / np.sqrt(1.0 + slope * slope)
    incidence = np.where(kin[:, None, :] >= lo, kcos[:, None, :] * cos_e[:, :, None], np.abs(slope * cos_e)[:, :, None])
    porous = por[:, None, :] > 0
    if porous.any():
        u = rng.random(hit.shape)
        hit &= ~(porous & (u < por[:, None, :]))
        # Where a ray that does not pass stops: a porous shape is a uniform medium that lets ``porosity`` of the
        # rays through its whole chord, so the stop is exponential along the chord with mu * chord = -ln(porosity)
        # (a crown is seen through its depth, not only on the face towards the sensor).
        with np.errstate(invalid="ignore", divide="ignore"):
            chord = np.maximum(leave - enter, 0.0)
            p_pass = np.clip(por[:, None, :], 1e-6, 1.0 - 1e-6)
            frac = -np.log1p(-rng.random(hit.shape) * (1.0 - p_pass)) / -np.log(p_pass)
            depth = np.where(hit & porous, chord * np.clip(frac, 0.0, 1.0), 0.0)
        enter = enter + depth
    rough = relief[:, None, :] > 0
    if rough.any():
        with np.errstate(invalid="ignore"):
            enter = enter + np.where(hit & rough, relief[:, None, :] * rng.random(hit.shape), 0.0)
    d_obj = np.where(hit, enter, np.inf)
    if d_obj.shape[2]:
        kbest = np.argmin(d_obj, axis=2)
        d_obj_min = np.take_along_axis(d_obj, kbest[..., None], axis=2)[..., 0]
        own_b = np.take_along_axis(np.broadcast_to(own[:, None, :], d_obj.shape), kbest[..., None], 2)[..., 0]
        refl_b = np.take_along_axis(np.broadcast_to(refl[:, None, :], d_obj.shape), kbest[..., None], 2)[..., 0]
        inc_b = np.take_along_axis(incidence, kbest[..., None], 2)[..., 0]
        por_b = np.take_along_axis(np.broadcast_to(por[:, None, :], d_obj.shape), kbest[..., None], 2)[..., 0]
    else:
        d_obj_min = np.full(slope.shape, np.inf)
        own_b = np.full(slope.shape, -1)
        refl_b = np.zeros(slope.shape)
        inc_b = np.ones(slope.shape)
        por_b = np.zeros(slope.shape)
    d_ground = _ground_hits(world, ox, oy, dx, dy, z0, slope, sensor.max_range_m, rng)
    on_ground = d_ground < d_obj_min
    d = np.where(on_ground, d_ground, d_obj_min)
    owner = np.where(on_ground, -2, own_b)
    reflect = np.where(on_ground, GROUND_REFLECTIVITY, refl_b)
    r = d * np.sqrt(1.0 + slope * slope)

    # Returns: range limits, dropout, and the detection range of each surface (sensors.SensorModel.reach_m): its
    # reflectivity times the cosine of incidence for a solid face (Lambertian); a porous medium (foliage) and the
    # rough ground scatter without a face to lean on, so their reflectivity counts in full.
    solid = ~on_ground & (por_b <= 0)
    lambert = np.where(solid, np.clip(inc_b, 0.0, 1.0) ** sensor.incidence_exponent, 1.0)
    p_keep = (1.0 - sensor.dropout) * sensor.detect_probability(r, reflect * lambert)
    keep = np.isfinite(r) & (r >= sensor.min_range_m) & (r <= sensor.max_range_m) & (rng.random(r.shape) < p_keep)
    ci, bi = np.nonzero(keep)
    rr = r[ci, bi] + rng.normal(0.0, sensor.range_noise_m, len(ci))
    e_rep, a_rep = elev[bi], az[ci]  # reported with the nominal angles, in the sensor frame of firing time
    pts = np.empty((len(ci), 4), dtype=np.float32)
    pts[:, 0] = rr * np.cos(e_rep) * np.cos(a_rep)
    pts[:, 1] = rr * np.cos(e_rep) * np.sin(a_rep)
    pts[:, 2] = rr * np.sin(e_rep)
    pts[:, 3] = np.clip(reflect[ci, bi] * rng.uniform(0.8, 1.2, len(ci)), 0.0, 1.0)
    return pts, owner[ci, bi].astype(np.int64), t_col[ci]
