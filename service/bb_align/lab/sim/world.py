"""Procedural streets: roads with curves and intersections, buildings, walls, trees, poles, bushes, cars.

Everything standing is an extruded footprint (the LiDAR ray caster's two primitives):
- prisms: oriented rectangles (centre, half length, half width, yaw) between heights zb and zt (buildings,
  walls, guard rails, car bodies and cabins, signs);
- cylinders: circles (centre, radius) between zb and zt (poles, trunks, tree crowns, bushes).
A ``porosity`` in [0, 1) lets a fraction of rays pass (vegetation); ``relief`` (metres) scatters the hit depth
behind the footprint's face (facade detail: recessed windows, balconies, pillars). The ground is a height field
(flat roads, raised sidewalks, gently rolling verges) with a grass layer that catches grazing rays.

The generator lives in ``streets``; this module holds the data types.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import map_coordinates

from .paths import Path


@dataclass
class Shapes:
    """Column arrays of the scene's primitives (one row per prism or cylinder)."""

    kind: list[str] = field(default_factory=list)  # "prism" | "cyl"
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    a: list[float] = field(default_factory=list)  # prism half length | cylinder radius
    b: list[float] = field(default_factory=list)  # prism half width | unused (0)
    yaw: list[float] = field(default_factory=list)
    zb: list[float] = field(default_factory=list)
    zt: list[float] = field(default_factory=list)
    porosity: list[float] = field(default_factory=list)
    reflect: list[float] = field(default_factory=list)
    relief: list[float] = field(default_factory=list)

    def prism(self, x, y, hl, hw, yaw, zb, zt, porosity=0.0, reflect=0.4, relief=0.0):
        self._add("prism", x, y, hl, hw, yaw, zb, zt, porosity, reflect, relief)

    def cyl(self, x, y, r, zb, zt, porosity=0.0, reflect=0.3, relief=0.0):
        self._add("cyl", x, y, r, 0.0, 0.0, zb, zt, porosity, reflect, relief)

    def _add(self, *vals):
        for name, v in zip(("kind", "x", "y", "a", "b", "yaw", "zb", "zt", "porosity", "reflect", "relief"), vals):
            getattr(self, name).append(v if name == "kind" else float(v))

    def arrays(self) -> ShapeArrays:
        is_cyl = np.array([k == "cyl" for k in self.kind], dtype=bool)
        f = lambda v: np.asarray(v, dtype=np.float64)  # noqa: E731
        return ShapeArrays(
            is_cyl,
            np.stack([f(self.x), f(self.y)], 1).reshape(-1, 2),
            f(self.a),
            f(self.b),
            f(self.yaw),
            f(self.zb),
            f(self.zt),
            f(self.porosity),
            f(self.reflect),
            f(self.relief),
            np.full(len(self.kind), -1, dtype=np.int64),
        )


@dataclass
class ShapeArrays:
    is_cyl: np.ndarray
    xy: np.ndarray  # (M, 2)
    a: np.ndarray
    b: np.ndarray
    yaw: np.ndarray
    zb: np.ndarray
    zt: np.ndarray
    porosity: np.ndarray
    reflect: np.ndarray
    relief: np.ndarray
    owner: np.ndarray  # vehicle index or -1 (static)

    def __len__(self) -> int:
        return len(self.a)

    @property
    def radius(self) -> np.ndarray:
        """Horizontal bounding radius of each footprint."""
        return np.where(self.is_cyl, self.a, np.hypot(self.a, self.b))

    def take(self, idx) -> ShapeArrays:
        return ShapeArrays(*(getattr(self, n)[idx] for n in self.__dataclass_fields__))

    @staticmethod
    def concat(parts: list[ShapeArrays]) -> ShapeArrays:
        names = list(ShapeArrays.__dataclass_fields__)
        return ShapeArrays(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))


@dataclass
class Road:
    centre: Path
    lanes_per_dir: int
    lane_width: float
    parking: float  # width of the parking strip on each side (0: none)
    sidewalk: float
    _lanes: dict = field(default_factory=dict, repr=False)

    @property
    def half_width(self) -> float:
        return self.lanes_per_dir * self.lane_width + self.parking

    def lane(self, k: int, forward: bool) -> Path:
        """Lane k (0 = next to the centre line) in the given direction; right-hand traffic."""
        if (k, forward) not in self._lanes:
            off = (k + 0.5) * self.lane_width
            self._lanes[k, forward] = self.centre.offset(-off) if forward else self.centre.offset(off).reversed()
        return self._lanes[k, forward]

    def lanes(self) -> list[Path]:
        return [self.lane(k, f) for f in (True, False) for k in range(self.lanes_per_dir)]


@dataclass
class Vehicle:
    """A car, van or truck. Static cars have ``path`` None and a fixed pose."""

    vid: int
    length: float
    width: float
    height: float
    kind: str
    path: Path | None = None
    s0: float = 0.0
    speed: float = 0.0
    pose0: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y, yaw when static
    z0: float = 0.0  # ground height under a static car

    def pose(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) of the box centre at times t (seconds, arrays allowed)."""
        t = np.asarray(t, dtype=float)
        if self.path is None:
            x, y, yaw = self.pose0
            return np.full(t.shape, x), np.full(t.shape, y), np.full(t.shape, yaw)
        return self.path.pose_at(self.s0 + self.speed * t)

    def box(self, t: float) -> np.ndarray:
        """[x, y, z, l, w, h, yaw] in the world frame (z = box centre) at time t."""
        x, y, yaw = (float(v) for v in self.pose(t))
        return np.array([x, y, self.z0 + self.height / 2, self.length, self.width, self.height, yaw])


@dataclass
class Terrain:
    """Ground height and grass height (metres) on a regular grid; bilinear in between."""

    lo: np.ndarray  # (2,) world x, y of cell (0, 0)
    res: float
    height: np.ndarray  # (H, W)
    grass: np.ndarray  # (H, W)

    def _sample(self, grid: np.ndarray, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float)
        shape = xy.shape[:-1]
        ij = ((xy.reshape(-1, 2) - self.lo) / self.res).T
        return map_coordinates(grid, ij, order=1, mode="nearest").reshape(shape)

    def height_at(self, xy) -> np.ndarray:
        return self._sample(self.height, xy)

    def grass_at(self, xy) -> np.ndarray:
        return self._sample(self.grass, xy)


@dataclass
class World:
    roads: list[Road]
    static: ShapeArrays
    vehicles: list[Vehicle]
    terrain: Terrain
    style_of: list[str]

    def vehicle_shapes(self, t: float, exclude: set[int] = frozenset()) -> tuple[ShapeArrays, np.ndarray]:
        """Prisms of every vehicle at time t (a body and a cabin for cars), and each prism's velocity (M, 2)."""
        sh = Shapes()
        owners, vel = [], []
        eps = 0.05
        for i, v in enumerate(self.vehicles):
            if i in exclude:
                continue
            x, y, yaw = (float(a) for a in v.pose(t))
            if v.path is not None and v.speed > 0:
                x2, y2, _ = v.pose(t + eps)
                vx, vy = (float(x2) - x) / eps, (float(y2) - y) / eps
            else:
                vx = vy = 0.0
            refl = 0.15 + 0.7 * ((v.vid * 0.6180339) % 1.0)  # paint: dark to bright
            c, s = np.cos(yaw), np.sin(yaw)
            z = v.z0
            if v.kind == "car":
                sh.prism(x, y, v.length / 2, v.width / 2, yaw, z + 0.25, z + v.height * 0.62, reflect=refl)
                off = -0.08 * v.length
                sh.prism(
                    x + c * off,
                    y + s * off,
                    v.length * 0.27,
                    v.width * 0.44,
                    yaw,
                    z + v.height * 0.62,
                    z + v.height,
                    reflect=refl,
                )
                n = 2
            else:
                sh.prism(x, y, v.length / 2, v.width / 2, yaw, z + 0.3, z + v.height, reflect=refl)
                n = 1
            owners += [i] * n
            vel += [(vx, vy)] * n
        arr = sh.arrays()
        arr.owner = np.asarray(owners, dtype=np.int64)
        return arr, np.asarray(vel, dtype=float).reshape(-1, 2)
