"""Procedural street generator: a curved main road with 1-3 crossing streets and everything along them.

Both sides of every road are walked in ~150 m chunks, each of one neighbourhood style:
- city: continuous frontages of 8-35 m buildings split into parts of different heights and setbacks, street
  trees, poles, signs, bins;
- suburb: low houses with yards (trees, hedges, bushes, fences), driveways with cars;
- industrial: large low halls, walls, yards with parked cars;
- open: few landmarks (empty verge, bushes, a fence, a guard rail, a few trees, a strip of woods, a parking lot).
Gaps and alleys between buildings let the LiDAR see second rows. The ground rolls gently off the road and
carries grass. Parked cars line kerbs and fill lots; moving traffic follows lanes (right-hand traffic).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt, gaussian_filter

from .paths import Path, build_centreline, straight
from .world import Road, Shapes, Terrain, Vehicle, World

STYLES = ("city", "suburb", "industrial", "open")
STYLE_WEIGHTS = (0.3, 0.3, 0.2, 0.2)
# A residential street as on the real far pairs (KITTI 00): houses with yards, some facades, parked cars on both
# sides; its property-line walls and hedges broken by driveways and gates more often than elsewhere.
RESIDENTIAL_WEIGHTS = (0.6, 0.4, 0.0, 0.0)
RESIDENTIAL_LINE_GAPS = 0.6
# Share of a residential frontage that is built (the rest: alleys and driveways, never open land): the real street
# is a canyon of facades that hides what stands behind them (docs/sim/street_real_vs_sim.png).
RESIDENTIAL_FRONTAGE = 0.9
# Blocks of a residential street (its building line and how full its kerbs are change from one to the next), m:
# a street changes from block to block, so that one place does not look like the next 75 m on.
RESIDENTIAL_BLOCK_M = (50.0, 120.0)
# What a residential kerb holds besides houses (per metre of street, each side), chosen on the lit-pixel profile of
# the real KITTI 00 scans within 40 m (docs/simulation.md): front-garden shrubs in irregular clumps, bins and bikes,
# lot dividers (fences and hedges running back from the street between houses), porches and bays on facades.
RESIDENTIAL_SHRUB_CLUMPS = 1 / 7.0
RESIDENTIAL_SMALL_THINGS = 1 / 9.0
RESIDENTIAL_LOT_DIVIDERS = 1 / 60.0
# How full a residential block's kerbs are (drawn per block), and the share of those cars kept whatever the
# traffic: KITTI 00's kerbs are lined with cars, 3-5 x the sim's lit pixels within the carriageway before.
RESIDENTIAL_KERB_OCCUPANCY = (0.6, 1.0)
RESIDENTIAL_PARKED_KEPT = 0.9
# Junctions of a residential street: real residential blocks are ~80-200 m long, so a car following another 75 m
# ahead usually has a junction near one of them. A side street to one side (a T) or a crossing; a share of them
# diagonal (30-60 deg between the streets, as the real KITTI 00 street's fork), the rest 80-100 deg.
RESIDENTIAL_JUNCTION_M = (80.0, 200.0)
RESIDENTIAL_CROSSING = 0.4
RESIDENTIAL_DIAGONAL = 0.25
RESIDENTIAL_ARM_M = (60.0, 150.0)
# Share of a residential street's blocks with a row of street trees along the kerb (each side; 0.6 elsewhere):
# crowns at the kerb hide the facades further along the street, and with 0.6 the pose landscape at the true pose
# had no bounded peak in 11 of 40 pairs (0.25: 7 of 40; the real KITTI 00 pairs: 0 of 20).
RESIDENTIAL_STREET_TREES = 0.25
# Cross-section of a residential street beyond its carriageway and parking strip (metres): sidewalk width and the
# houses' building line behind it (drawn per block). Chosen on the nearest thing taller than a car beside each scan's
# axis (realism.nearest_tall_m, median left / right): KITTI 00's street 8.6 / 5.4 m, the street family 11.0 / 8.2
# with a 2-4 m sidewalk and a 1-5 m building line, 9.8 / 6.2 with these; held out, KITTI 08's street 8.6 / 4.6 and
# its loop 7.0 / 4.2 (docs/simulation.md).
RESIDENTIAL_SIDEWALK_M = (1.5, 2.5)
RESIDENTIAL_BUILDING_LINE_M = (0.0, 2.5)
FAMILIES = ("mixed", "street", "turn", "crossing")
# Reflectivity at the LiDARs' 905 nm (what sensors.SensorModel.reach_m reads): green leaves reflect about half of
# the near infrared (their NIR plateau), plaster, brick and concrete facades 0.3-0.8; bark, asphalt and dark paint
# less. The HDL-64E datasheet's 80 % targets are "cars and foliage".
FOLIAGE_REFLECTIVITY = 0.55
FACADE_REFLECTIVITY = (0.3, 0.8)


class _Occupancy:
    """1 m raster of the world used while placing things: road corridors and ground already taken."""

    def __init__(self, roads: list[Road], res: float = 1.0, margin: float = 150.0):
        pts = np.concatenate([r.centre.xy for r in roads])
        self.lo = pts.min(0) - margin
        hi = pts.max(0) + margin
        self.res = res
        self.shape = tuple(np.ceil((hi - self.lo) / res).astype(int) + 1)
        self.corridor, self.carriage = [], []  # per road: carriageway + sidewalk; carriageway only
        for r in roads:
            seed = np.ones(self.shape, dtype=bool)
            ij = self.ij(r.centre.xy)
            seed[ij[:, 0], ij[:, 1]] = False
            dist = distance_transform_edt(seed) * res
            self.corridor.append(dist <= r.half_width + r.sidewalk)
            self.carriage.append(dist <= r.half_width + 0.5)
        self.any_corridor = np.logical_or.reduce(self.corridor)
        self.any_carriage = np.logical_or.reduce(self.carriage)
        self._other = [
            np.logical_or.reduce([m for j, m in enumerate(self.carriage) if j != i])
            if len(roads) > 1
            else np.zeros(self.shape, dtype=bool)
            for i in range(len(roads))
        ]
        self.taken = np.zeros(self.shape, dtype=bool)

    def ij(self, xy) -> np.ndarray:
        ij = np.floor((np.asarray(xy, dtype=float).reshape(-1, 2) - self.lo) / self.res).astype(int)
        return np.clip(ij, 0, np.array(self.shape) - 1)

    def at(self, mask: np.ndarray, x: float, y: float) -> bool:
        i, j = self.ij([x, y])[0]
        return bool(mask[i, j] or self.taken[i, j])

    def rect_cells(self, x, y, hl, hw, yaw) -> np.ndarray:
        u, v = np.meshgrid(np.arange(-hl, hl + 0.01, 0.7), np.arange(-hw, hw + 0.01, 0.7))
        c, s = np.cos(yaw), np.sin(yaw)
        return self.ij(np.stack([x + c * u.ravel() - s * v.ravel(), y + s * u.ravel() + c * v.ravel()], 1))

    def claim_rect(self, x, y, hl, hw, yaw, mask) -> bool:
        """Take a rectangle of ground if it is clear of ``mask`` and of earlier claims."""
        ij = self.rect_cells(x, y, hl, hw, yaw)
        if mask[ij[:, 0], ij[:, 1]].any() or self.taken[ij[:, 0], ij[:, 1]].any():
            return False
        self.taken[ij[:, 0], ij[:, 1]] = True
        return True

    def other_carriage(self, road_idx: int) -> np.ndarray:
        """Carriageways of every road but this one (things along one road must not block another)."""
        return self._other[road_idx]


class _Side:
    """Placement helper for one side of one road: positions by arc length and lateral offset."""

    def __init__(
        self,
        sh: Shapes,
        occ: _Occupancy,
        rng,
        road: Road,
        road_idx: int,
        side: int,
        parked: list,
        weights: tuple[float, ...] = STYLE_WEIGHTS,
        line_gaps: float = 0.25,
        residential: bool = False,
    ):
        self.weights, self.line_gaps, self.residential = weights, line_gaps, residential
        self.sh, self.occ, self.rng, self.road, self.idx, self.side, self.parked = (
            sh,
            occ,
            rng,
            road,
            road_idx,
            side,
            parked,
        )
        self.edge = road.half_width + road.sidewalk  # property line, from the centre line
        # setback of this side's houses
        self.building_line = float(rng.uniform(*RESIDENTIAL_BUILDING_LINE_M)) if residential else 0.0

    def at(self, s: float, lat: float) -> tuple[float, float, float]:
        """World (x, y, road heading) at arc length s, ``lat`` metres out from the centre line on this side."""
        x, y, yaw = (float(v) for v in self.road.centre.pose_at(s))
        lat *= self.side
        return x - np.sin(yaw) * lat, y + np.cos(yaw) * lat, yaw

    def free(self, x, y, kerb=False) -> bool:
        mask = self.occ.other_carriage(self.idx) if kerb else self.occ.any_corridor
        return not self.occ.at(mask, x, y)

    # -- things ----------------------------------------------------------------------------------------------
    def tree(self, x, y, scale=1.0):
        """Trunk plus a rounded, porous crown (two stacked cylinders)."""
        r = self.rng
        h_trunk = r.uniform(1.8, 3.2) * scale
        r_crown = r.uniform(1.5, 3.8) * scale
        h_crown = r.uniform(2.5, 7.0) * scale
        self.sh.cyl(x, y, r.uniform(0.12, 0.3) * scale, 0.0, h_trunk + 0.5, reflect=0.25)
        z1 = h_trunk + 0.55 * h_crown
        self.sh.cyl(x, y, r_crown, h_trunk, z1, porosity=r.uniform(0.35, 0.65), reflect=FOLIAGE_REFLECTIVITY)
        jx, jy = r.normal(0, 0.3 * scale, 2)
        self.sh.cyl(
            x + jx,
            y + jy,
            r_crown * r.uniform(0.55, 0.8),
            z1,
            h_trunk + h_crown,
            porosity=r.uniform(0.35, 0.65),
            reflect=FOLIAGE_REFLECTIVITY,
        )

    def bush(self, x, y, big=1.0):
        r = self.rng
        self.sh.cyl(
            x,
            y,
            r.uniform(0.4, 1.6) * big,
            0.0,
            r.uniform(0.5, 1.9) * big,
            porosity=r.uniform(0.2, 0.5),
            reflect=FOLIAGE_REFLECTIVITY,
        )

    def wall(self, s0, s1, lat, h, thick=0.15, zb=0.0, porosity=0.0, step=6.0, gap_prob=0.0):
        """A fence / wall / hedge / rail following the road in short straight pieces (some left out as gaps)."""
        for a in np.arange(s0, s1 - 1.0, step):
            if gap_prob and self.rng.random() < gap_prob:
                continue
            b = min(a + step, s1)
            x, y, yaw = self.at((a + b) / 2, lat)
            if self.free(x, y, kerb=True):
                self.sh.prism(x, y, (b - a) / 2, thick, yaw, zb, h, porosity=porosity, reflect=0.45)

    def park(self, x, y, yaw):
        self.parked.append((x, y, yaw))

    def furniture(self, s0, s1, dense: bool):
        """Poles, signs, bins and hydrants on the sidewalk."""
        r = self.rng
        lat = self.edge - 0.5
        spacing = r.uniform(25, 45)
        for sp in np.arange(s0 + r.uniform(0, spacing), s1, spacing):
            x, y, _ = self.at(sp, lat)
            if self.free(x, y, kerb=True):
                self.sh.cyl(x, y, r.uniform(0.1, 0.2), 0.0, r.uniform(5, 9), reflect=0.6)
        for _ in range(int(r.poisson((s1 - s0) / (20 if dense else 60)))):
            sp = r.uniform(s0, s1)
            x, y, yaw = self.at(sp, self.edge - r.uniform(0.3, 1.2))
            if not self.free(x, y, kerb=True):
                continue
            kind = r.random()
            if kind < 0.4:  # sign: post and plate
                self.sh.cyl(x, y, 0.04, 0.0, 2.2, reflect=0.5)
                self.sh.prism(x, y, 0.35, 0.04, yaw + np.pi / 2, 2.0, 2.7, reflect=0.9)
            elif kind < 0.75:  # bin / hydrant / utility box
                self.sh.prism(x, y, r.uniform(0.25, 0.6), r.uniform(0.25, 0.5), yaw, 0.0, r.uniform(0.7, 1.4))
            else:  # bus shelter / kiosk
                self.sh.prism(x, y, r.uniform(1.5, 3.0), 0.7, yaw, 0.0, 2.6, porosity=0.5)

    def building(self, s, frontage, style):
        """1-4 buildings of different heights, depths and setbacks along a frontage."""
        r = self.rng
        n_parts = int(r.integers(1, 5)) if frontage > 16 else 1
        bounds = np.concatenate([[0.0], np.sort(r.uniform(0, frontage, n_parts - 1)), [frontage]])
        base_h = {"city": r.uniform(8, 32), "suburb": r.uniform(3.5, 8), "industrial": r.uniform(5, 12)}[style]
        base_set = r.uniform(0.3, 2.5) if style == "city" else r.uniform(3, 14)
        jitter, skew = (0.8 if style == "city" else 2.5), np.radians(2)
        if self.residential:  # houses on the street's common building line, as planned streets are laid out
            base_set, jitter, skew = self.building_line, 0.3, np.radians(0.5)
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < 4:
                continue
            setback = max(0.2, base_set + r.normal(0, jitter))
            depth = {"city": r.uniform(12, 30), "suburb": r.uniform(8, 14), "industrial": r.uniform(15, 45)}[style]
            cx, cy, yaw = self.at(s + (a + b) / 2, self.edge + setback + depth / 2)
            hl, hw = (b - a) / 2 - r.uniform(0, 0.8), depth / 2
            yaw_b = yaw + r.normal(0, skew)
            if not self.occ.claim_rect(cx, cy, hl, hw, yaw_b, self.occ.any_corridor):
                continue
            h = max(3.0, base_h * r.uniform(0.6, 1.4))
            relief = {"city": r.uniform(0.2, 1.0), "suburb": r.uniform(0.1, 0.6), "industrial": r.uniform(0.05, 0.3)}
            self.sh.prism(cx, cy, hl, hw, yaw_b, 0.0, h, reflect=r.uniform(*FACADE_REFLECTIVITY), relief=relief[style])
            if self.residential:
                self.bays(cx, cy, hl, hw, yaw_b, h)
            if r.random() < 0.4:  # annex, porch or stepped roof
                off = self.side * hw * r.uniform(0.3, 0.9)
                self.sh.prism(
                    cx - np.sin(yaw_b) * off,
                    cy + np.cos(yaw_b) * off,
                    hl * r.uniform(0.3, 0.7),
                    hw * 0.6,
                    yaw_b,
                    0.0,
                    h * r.uniform(0.3, 1.6),
                    reflect=r.uniform(*FACADE_REFLECTIVITY),
                    relief=relief[style],
                )
            if r.random() < {"city": 0.7, "suburb": 0.5, "industrial": 0.4}[style]:  # a second row behind
                depth2 = depth * r.uniform(0.6, 1.3)
                lat2 = self.edge + setback + depth + r.uniform(3, 15) + depth2 / 2
                x2, y2, _ = self.at(s + (a + b) / 2 + r.normal(0, 3), lat2)
                hl2 = hl * r.uniform(0.6, 1.2)
                if self.occ.claim_rect(x2, y2, hl2, depth2 / 2, yaw_b, self.occ.any_corridor):
                    self.sh.prism(
                        x2,
                        y2,
                        hl2,
                        depth2 / 2,
                        yaw_b + r.normal(0, 0.03),
                        0.0,
                        max(3.0, base_h * r.uniform(0.5, 1.6)),
                        reflect=r.uniform(*FACADE_REFLECTIVITY),
                        relief=relief[style],
                    )
            if style == "suburb":
                self._yard(s + a, s + b, setback)
                self._yard(s + a, s + b, setback + depth + r.uniform(2, 12))  # back yard
            elif style == "industrial" and r.random() < 0.5:
                self.wall(s + a, s + b, self.edge + 0.5, r.uniform(1.8, 3.0))

    def _yard(self, s0, s1, setback):
        r = self.rng
        for _ in range(int(r.integers(0, 4))):
            x, y, _ = self.at(r.uniform(s0, s1), self.edge + r.uniform(0.5, max(1.0, setback)))
            if self.free(x, y):
                (self.tree(x, y, r.uniform(0.6, 1.0)) if r.random() < 0.5 else self.bush(x, y))
        if r.random() < 0.35:  # hedge or fence on the property line
            self.wall(
                s0, s1, self.edge + 0.4, r.uniform(0.9, 2.0), thick=r.uniform(0.2, 0.5), porosity=r.uniform(0.1, 0.4)
            )
        if r.random() < 0.4:  # car in the driveway
            x, y, yaw = self.at(r.uniform(s0, s1), self.edge + r.uniform(2.5, max(3.0, setback - 2.5)))
            if self.free(x, y):
                self.park(x, y, yaw + np.pi / 2 * self.side + r.normal(0, 0.1))

    def kerb_parking(self, s0, s1):
        """Kerb-side cars packed as drivers leave them: gaps of 0.5-6 m, driveway breaks, a little skew and offset
        (a residential street's rows are irregular, unlike a lot's 6.3 m grid)."""
        r = self.rng
        sp = s0 + r.uniform(0, 4)
        occupancy = r.uniform(*RESIDENTIAL_KERB_OCCUPANCY)  # how full this block's kerb is
        while sp < s1:
            if r.random() < 0.12 or r.random() > occupancy:  # a driveway, a hydrant, or just a free space
                sp += r.uniform(4, 12)
                continue
            lat = self.road.half_width - self.road.parking / 2 + r.normal(0, 0.15)
            x, y, yaw = self.at(sp + 2.4, lat)
            if self.free(x, y, kerb=True):
                self.park(x, y, yaw + (np.pi if self.side > 0 else 0.0) + r.normal(0, 0.05))
            sp += 4.8 + 0.5 + r.exponential(1.8)

    def kerb_life(self, s0, s1):
        """The small, irregular things of a residential street's edge (RESIDENTIAL_* rates)."""
        r = self.rng
        for _ in range(int(r.poisson((s1 - s0) * RESIDENTIAL_SHRUB_CLUMPS))):  # clumps of garden shrubs
            cx, cy, _ = self.at(r.uniform(s0, s1), self.edge + r.uniform(0.4, 4.0))
            for _ in range(int(r.integers(2, 6))):
                x, y = cx + r.normal(0, 0.9), cy + r.normal(0, 0.9)
                if self.free(x, y):
                    h = r.uniform(0.4, 1.8)
                    self.sh.cyl(
                        x, y, r.uniform(0.25, 0.9), 0.0, h, porosity=r.uniform(0.15, 0.5), reflect=FOLIAGE_REFLECTIVITY
                    )
        for _ in range(int(r.poisson((s1 - s0) * RESIDENTIAL_SMALL_THINGS))):  # bins, bikes, boxes, low posts
            x, y, yaw = self.at(r.uniform(s0, s1), self.edge + r.uniform(-1.5, 2.5))
            if not self.free(x, y, kerb=True):
                continue
            kind = r.random()
            if kind < 0.4:  # wheelie bin
                self.sh.prism(x, y, 0.3, 0.3, yaw + r.normal(0, 0.3), 0.0, 1.05, reflect=r.uniform(0.1, 0.5))
            elif kind < 0.7:  # parked bike: a porous frame
                self.sh.prism(x, y, 0.85, 0.25, yaw + r.uniform(0, np.pi), 0.0, 1.05, porosity=0.6, reflect=0.5)
            else:  # post, bollard, electricity box
                self.sh.prism(x, y, r.uniform(0.1, 0.5), r.uniform(0.1, 0.3), yaw, 0.0, r.uniform(0.8, 1.6))
        for _ in range(int(r.poisson((s1 - s0) * RESIDENTIAL_LOT_DIVIDERS))):  # fence or hedge between two lots
            depth = r.uniform(4, 18)
            x, y, yaw = self.at(r.uniform(s0, s1), self.edge + 0.3 + depth / 2)
            if self.free(x, y):
                hedge = r.random() < 0.5
                self.sh.prism(
                    x,
                    y,
                    depth / 2,
                    r.uniform(0.2, 0.6) if hedge else 0.05,
                    yaw + np.pi / 2 + r.normal(0, 0.05),
                    0.0,
                    r.uniform(1.0, 2.2),
                    porosity=r.uniform(0.2, 0.4) if hedge else r.uniform(0.0, 0.5),
                    reflect=0.45,
                )

    def bays(self, cx, cy, hl, hw, yaw_b, h):
        """Porches, bays and garages on the street face of a house (real facades are broken)."""
        r = self.rng
        for _ in range(int(r.integers(0, 3))):
            u = r.uniform(-hl * 0.8, hl * 0.8)
            out = r.uniform(0.3, 1.2)
            off = -self.side * (hw + out / 2)  # towards the street
            c, s_ = np.cos(yaw_b), np.sin(yaw_b)
            x, y = cx + c * u - s_ * off, cy + s_ * u + c * off
            self.sh.prism(x, y, r.uniform(0.8, 2.5), out / 2, yaw_b, 0.0, min(h, r.uniform(2.5, 4.5)), reflect=0.4)

    def open_stretch(self, s, length):
        """Few landmarks: nothing, bushes, a fence or wall, a guard rail, a few trees, woods, a parking lot."""
        r = self.rng
        kind = r.choice(
            ["empty", "bushes", "fence", "rail", "trees", "woods", "lot"], p=[0.22, 0.18, 0.14, 0.12, 0.14, 0.1, 0.1]
        )
        if kind == "bushes":
            for _ in range(int(r.integers(3, 14))):
                x, y, _ = self.at(s + r.uniform(0, length), self.edge + r.uniform(1, 25))
                if self.free(x, y):
                    self.bush(x, y, big=r.uniform(0.7, 1.3))
        elif kind == "fence":
            self.wall(
                s,
                s + length,
                self.edge + r.uniform(0.5, 4),
                r.uniform(1.2, 2.8),
                porosity=0.3 if r.random() < 0.5 else 0.0,
            )
        elif kind == "rail":
            self.wall(s, s + length, self.road.half_width + 0.4, 0.8, thick=0.1, zb=0.35)
        elif kind in ("trees", "woods"):
            n = int(r.integers(2, 7)) if kind == "trees" else int(length * r.uniform(0.3, 0.6))
            depth = 30 if kind == "trees" else r.uniform(15, 40)
            for _ in range(n):
                x, y, _ = self.at(s + r.uniform(0, length), self.edge + r.uniform(1, depth))
                if self.free(x, y):
                    self.tree(x, y, r.uniform(0.7, 1.2)) if r.random() < 0.75 else self.bush(x, y)
        elif kind == "lot":
            for row in range(int(r.integers(1, 4))):
                for sp in np.arange(s + 2, s + length - 2, 2.7):
                    if r.random() < 0.45:
                        continue
                    x, y, yaw = self.at(sp, self.edge + 3 + row * 6.5)
                    if self.free(x, y):
                        self.park(x, y, yaw + np.pi / 2 + r.normal(0, 0.05) + np.pi * (r.random() < 0.5))

    def walk(self) -> list[str]:
        r = self.rng
        styles = []
        L = self.road.centre.length
        s = 0.0
        while s < L:
            style = str(r.choice(STYLES, p=self.weights))
            styles.append(style)
            end = min(L, s + (r.uniform(*RESIDENTIAL_BLOCK_M) if self.residential else 150.0))
            if self.residential:  # each block its own building line
                self.building_line = float(r.uniform(*RESIDENTIAL_BUILDING_LINE_M))
            if style != "open" or r.random() < 0.3:
                self.furniture(s, end, dense=style == "city")
            street_trees = RESIDENTIAL_STREET_TREES if self.residential else 0.6
            if style in ("suburb", "city") and r.random() < street_trees:
                spacing = r.uniform(7, 15)
                for sp in np.arange(s + r.uniform(0, spacing), end, spacing):
                    x, y, _ = self.at(sp, self.edge - self.road.sidewalk / 2)
                    if r.random() > 0.2 and self.free(x, y, kerb=True):
                        self.tree(x, y, scale=r.uniform(0.7, 1.1))
            if style != "open" and r.random() < 0.5:  # low wall, hedge or fence along the property line
                kind = r.integers(3)  # wall, hedge, fence
                height = (r.uniform(0.6, 1.2), r.uniform(0.8, 2.0), r.uniform(1.0, 2.2))[kind]
                self.wall(
                    s,
                    end,
                    self.edge + 0.3,
                    height,
                    thick=(0.2, r.uniform(0.3, 0.8), 0.05)[kind],
                    porosity=(0.0, 0.3, 0.5)[kind],
                    gap_prob=self.line_gaps,
                )
            for _ in range(int(r.poisson((end - s) / {"city": 12, "suburb": 60}.get(style, 120)))):  # people
                x, y, _ = self.at(r.uniform(s, end), self.edge - r.uniform(0.3, self.road.sidewalk - 0.2))
                if self.free(x, y, kerb=True):
                    self.sh.cyl(x, y, r.uniform(0.2, 0.3), 0.0, r.uniform(1.5, 1.9), reflect=0.3)
            if self.residential:
                self.kerb_life(s, end)
                self.kerb_parking(s, end)
            elif self.road.parking > 0 and r.random() < 0.85:  # kerb-side parking
                for sp in np.arange(s, end, 6.3):
                    x, y, yaw = self.at(sp, self.road.half_width - self.road.parking / 2)
                    if r.random() > 0.3 and self.free(x, y, kerb=True):
                        self.park(x, y, yaw + (np.pi if self.side > 0 else 0.0) + r.normal(0, 0.03))
            while s < end:
                if style == "open":
                    length = min(end - s, r.uniform(30, 120))
                    self.open_stretch(s, length)
                    s += length
                elif r.random() < (RESIDENTIAL_FRONTAGE if self.residential else 0.75):
                    frontage = r.uniform(12, 50) if style != "suburb" else r.uniform(12, 22)
                    self.building(s, frontage, style)
                    s += frontage
                elif self.residential or r.random() < 0.6:
                    s += r.uniform(3, 15)  # alley or driveway
                else:
                    length = r.uniform(15, 50)
                    self.open_stretch(s, length)
                    s += length
        return styles


def _vehicle_dims(rng) -> tuple[float, float, float, str]:
    u = rng.random()
    if u < 0.72:
        return rng.uniform(4.1, 4.9), rng.uniform(1.72, 1.95), rng.uniform(1.4, 1.6), "car"
    if u < 0.94:
        return rng.uniform(4.8, 5.4), rng.uniform(1.9, 2.1), rng.uniform(1.7, 2.1), "van"
    return rng.uniform(8.0, 12.5), rng.uniform(2.4, 2.6), rng.uniform(2.9, 3.6), "truck"


def _vegetation(sh: Shapes, occ: _Occupancy, rng, roads: list[Road]) -> None:
    """Scattered trees and bushes over the free ground within ~120 m of the roads (density drawn per world)."""
    density = rng.uniform(0.0004, 0.0025)  # plants per square metre of free ground
    free = ~(occ.any_corridor | occ.taken)
    near = distance_transform_edt(~occ.any_corridor[::4, ::4]) * 4 * occ.res < 120
    area = near.sum() * (4 * occ.res) ** 2
    n = int(rng.poisson(density * area))
    cand = np.argwhere(near)
    if not len(cand) or not n:
        return
    pick = cand[rng.integers(0, len(cand), n)] * 4 + rng.integers(0, 4, (n, 2))
    pick = np.clip(pick, 0, np.array(occ.shape) - 1)
    side = _Side(sh, occ, rng, roads[0], 0, 1, [])
    for i, j in pick[free[pick[:, 0], pick[:, 1]]]:
        x, y = occ.lo + (np.array([i, j]) + 0.5) * occ.res
        clump = int(rng.integers(1, 4))
        for _ in range(clump):
            px, py = x + rng.normal(0, 2.5), y + rng.normal(0, 2.5)
            if side.free(px, py):
                side.tree(px, py, rng.uniform(0.6, 1.2)) if rng.random() < 0.55 else side.bush(px, py, 1.2)


def _terrain(occ: _Occupancy, rng, res: float = 2.0) -> Terrain:
    """Flat carriageways, kerbs 0.15 m up, verges rolling by up to ~1 m, grass 0-0.5 m."""
    step = int(round(res / occ.res))
    corridor = occ.any_corridor[::step, ::step]
    carriage = occ.any_carriage[::step, ::step]
    dist = distance_transform_edt(~corridor) * res
    noise = gaussian_filter(rng.normal(size=corridor.shape), sigma=7)
    noise /= noise.std() + 1e-9
    bumps = gaussian_filter(rng.normal(size=corridor.shape), sigma=2)
    bumps /= bumps.std() + 1e-9
    amp = rng.uniform(0.05, 0.5)
    rough = amp * (noise + 0.25 * bumps)
    height = rough * np.clip(dist / 10.0, 0, 1) + 0.15 * (corridor & ~carriage) + 0.15 * (~corridor)
    g = gaussian_filter(rng.normal(size=corridor.shape), sigma=4)
    g = np.clip(rng.uniform(0.02, 0.2) + 0.15 * g / (g.std() + 1e-9), 0, 0.5) * (~corridor)
    return Terrain(occ.lo.astype(float), res, height, g)


def _side_streets(rng, main: Path) -> list[Road]:
    """The junctions of a residential street: a side street every block (RESIDENTIAL_JUNCTION_M), to one side (a T)
    or through (a crossing), most near square, some diagonal; each a residential street of its own."""
    roads = []
    s = float(rng.uniform(0.0, RESIDENTIAL_JUNCTION_M[1]))
    while s < main.length - 20.0:
        x, y, yaw = (float(v) for v in main.pose_at(s))
        diagonal = rng.random() < RESIDENTIAL_DIAGONAL
        ang = yaw + np.radians(rng.uniform(*((30, 60) if diagonal else (80, 100)))) * rng.choice([-1, 1])
        arm = float(rng.uniform(*RESIDENTIAL_ARM_M))
        if rng.random() < RESIDENTIAL_CROSSING:  # through the main road
            c = straight((x - arm * np.cos(ang), y - arm * np.sin(ang)), ang, 2 * arm)
        else:  # a T: from the main road's centre line out to one side
            c = straight((x, y), ang, arm)
        roads.append(Road(c, 1, 3.0, 2.0, float(rng.uniform(1.5, 3.0))))
        s += float(rng.uniform(*RESIDENTIAL_JUNCTION_M))
    return roads


def generate_world(
    rng: np.random.Generator, main_length_m: float = 650.0, traffic: float | None = None, family: str = "mixed"
) -> World:
    """A street network (a curved main road and 1-3 crossing streets) with everything along it.

    ``traffic`` in [0, 1] scales the number of parked and moving cars (None: drawn per world). ``family``:
    "mixed" (the benchmark's), "street" (a straight residential main road, one lane each way, parked cars along
    both kerbs, facades and yards on both sides: a car following another on it is the real far pairs' case) or
    "turn" (a straight main road whose crossings meet it at 65-115 deg: for a car that has turned off ahead);
    "crossing" draws the same worlds as "turn" (only the cars' placement differs, scenario.py).
    """
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if family == "mixed":
        main = build_centreline(rng, main_length_m, start_heading=float(rng.uniform(-np.pi, np.pi)))
    else:  # straight to the eye: a 1.5-5 km radius turns a car 1-3 deg over 80 m, as on real streets
        h0, bend = float(rng.uniform(-np.pi, np.pi)), float(rng.choice([-1, 1]) / rng.uniform(1500.0, 5000.0))
        s = np.arange(0.0, main_length_m + 0.25, 0.5)
        h = h0 + bend * s
        main = Path.from_points(np.stack([np.cumsum(np.cos(h)) * 0.5, np.cumsum(np.sin(h)) * 0.5], axis=1))
    street = family == "street"
    roads = [
        Road(
            main,
            1 if street else int(rng.integers(1, 3)),
            3.5,
            2.5 if street else float(rng.choice([0.0, 2.5], p=[0.4, 0.6])),
            float(rng.uniform(*(RESIDENTIAL_SIDEWALK_M if street else (2, 4)))),
        )
    ]
    for _ in range(0 if street else int(rng.integers(1, 4))):
        s_x = float(rng.uniform(120, main.length - 120))
        x, y, yaw = (float(v) for v in main.pose_at(s_x))
        ang = yaw + np.radians(rng.uniform(65, 115)) * rng.choice([-1, 1])
        half = float(rng.uniform(110, 180))
        c = straight((x - half * np.cos(ang), y - half * np.sin(ang)), ang, 2 * half)
        roads.append(
            Road(c, int(rng.integers(1, 3)), 3.5, float(rng.choice([0.0, 2.5], p=[0.4, 0.6])), float(rng.uniform(2, 4)))
        )
    if street:
        roads += _side_streets(rng, main)
    occ = _Occupancy(roads)
    sh = Shapes()
    parked: list[tuple[float, float, float]] = []
    styles: list[str] = []
    for i, road in enumerate(roads):
        for side in (-1, 1):
            if street:  # the side streets are residential too
                styles += _Side(
                    sh, occ, rng, road, i, side, parked, RESIDENTIAL_WEIGHTS, RESIDENTIAL_LINE_GAPS, residential=True
                ).walk()
            else:
                styles += _Side(sh, occ, rng, road, i, side, parked).walk()
    _vegetation(sh, occ, rng, roads)
    terrain = _terrain(occ, rng)
    static = sh.arrays()
    base = terrain.height_at(static.xy)  # stand things on the ground
    static.zb += base
    static.zt += base

    traffic = float(rng.uniform(0.2, 1.0)) if traffic is None else float(traffic)
    vehicles: list[Vehicle] = []
    # residents' cars stay at the kerb whatever the traffic (the real street's kerbs are nearly full)
    keep = rng.random(len(parked)) < (RESIDENTIAL_PARKED_KEPT if street else 0.35 + 0.65 * traffic)
    for (x, y, yaw), k in zip(parked, keep):
        if k:
            l, w, h, kind = _vehicle_dims(rng)
            if kind == "truck" and rng.random() < 0.7:
                l, w, h, kind = 4.5, 1.85, 1.5, "car"
            z0 = float(terrain.height_at(np.array([x, y])))
            vehicles.append(Vehicle(len(vehicles), l, w, h, kind, pose0=(x, y, yaw), z0=z0))
    for road in roads:
        for lane in road.lanes():
            speed = float(rng.uniform(5, 16))
            gap_mean = 15 + 120 * (1 - traffic)
            s = float(rng.uniform(0, gap_mean))
            while s < lane.length:
                l, w, h, kind = _vehicle_dims(rng)
                vehicles.append(Vehicle(len(vehicles), l, w, h, kind, path=lane, s0=s, speed=speed))
                s += l + 4 + rng.exponential(gap_mean)
    return World(roads, static, vehicles, terrain, styles)
