"""Log-Gabor filter bank and the Maximum Index Map (paper Eqs. 5-10, numbers from ALGORITHM.md).

The bank lives in the frequency domain and is built once per image shape (LRU cache). One forward FFT, then
per (scale, orientation) a complex inverse FFT (OpenCV's, float32: about twice as fast here as numpy/scipy's);
amplitudes are summed over scales and the MIM is 1 + the index of the strongest orientation (0 where the
strongest amplitude is negligible). The 1/(H W) of the inverse transform is folded into the cached bank.

Coarse scales are band-limited: a filter centred at 1/13 cycle/px is below 1 % of its peak beyond 0.19.
Such a scale is transformed on a smaller grid (the spectrum cropped to the filter's band: the inverse DFT then
gives the exact response at every (N/n)-th pixel) and its amplitude is interpolated back bilinearly
(``MimConfig.band_tolerance``; 0 computes every scale at full size).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import scipy.fft as sfft

from .config import MimConfig
from .parallel import run_parts


def frequency_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Radius r and angle theta of each FFT bin, in the unshifted (FFT) order; r[0, 0] = 1 (DC guard)."""
    rows, cols = shape
    v = sfft.fftfreq(rows)  # cycles/px along rows, in [-0.5, 0.5)
    u = sfft.fftfreq(cols)
    uu, vv = np.meshgrid(u, v)
    r = np.sqrt(uu**2 + vv**2)
    theta = np.arctan2(-vv, uu)
    r[0, 0] = 1.0
    return r, theta


def radial_filters(r: np.ndarray, cfg: MimConfig) -> np.ndarray:
    """(Ns, H, W) radial log-Gabor components times the Butterworth low-pass, zero at DC."""
    lowpass = 1.0 / (1.0 + (r / cfg.lowpass_cutoff) ** (2 * cfg.lowpass_order))
    out = np.empty((cfg.n_scales,) + r.shape)
    denom = 2.0 * np.log(cfg.sigma_on_f) ** 2
    for s in range(cfg.n_scales):
        f0 = 1.0 / (cfg.min_wavelength_px * cfg.mult**s)
        g = np.exp(-(np.log(r / f0) ** 2) / denom) * lowpass
        g[0, 0] = 0.0
        out[s] = g
    return out


def angular_filters(theta: np.ndarray, cfg: MimConfig) -> np.ndarray:
    """(No, H, W) raised-cosine angular windows centred at phi_o = o*pi/No, zero beyond pi/No."""
    out = np.empty((cfg.n_orient,) + theta.shape)
    for o in range(cfg.n_orient):
        phi = o * np.pi / cfg.n_orient
        dtheta = np.abs(np.arctan2(np.sin(theta - phi), np.cos(theta - phi)))
        dtheta = np.minimum(dtheta * cfg.n_orient, np.pi)
        out[o] = (np.cos(dtheta) + 1.0) / 2.0
    return out


@lru_cache(maxsize=8)
def filter_bank(shape: tuple[int, int], cfg: MimConfig) -> np.ndarray:
    """(No, Ns, H, W) complex64-ready float32 bank G_s * S_o for an FFT of ``shape``; cached per shape."""
    r, theta = frequency_grid(shape)
    radial = radial_filters(r, cfg)
    angular = angular_filters(theta, cfg)
    bank = (angular[:, None] * radial[None, :]).astype(np.float32)
    bank.setflags(write=False)
    return bank


def band_radius(scale: int, cfg: MimConfig) -> float:
    """Frequency (cycles/px) beyond which scale ``scale``'s radial filter stays below cfg.band_tolerance of its
    peak (0.5 = the whole band, also when the tolerance is 0)."""
    if cfg.band_tolerance <= 0:
        return 0.5
    f0 = 1.0 / (cfg.min_wavelength_px * cfg.mult**scale)
    return min(0.5, f0 * np.exp(abs(np.log(cfg.sigma_on_f)) * np.sqrt(2.0 * np.log(1.0 / cfg.band_tolerance))))


@dataclass(frozen=True)
class _Block:
    """One oriented filter on its grid: non-zero only on a 30-degree wedge of the plane (about 6 % of it), so
    only its circular bounding box (rows r0.., cols c0.., wrapping) is multiplied. The box is written at the
    grid's origin: shifting a spectrum only multiplies the response by a phase ramp, the amplitude is the same."""

    r0: int
    c0: int
    values: np.ndarray  # (bh, bw, 2) float32: the filter over the box, twice (re, im), times 1/(H W)


@dataclass(frozen=True)
class _Band:
    """Scales transformed on one n x n grid (n <= N): which frequencies of the N x N spectrum it keeps."""

    size: tuple[int, int]
    scales: tuple[int, ...]
    rows: np.ndarray  # indices into the full spectrum's rows (all when n = N)
    cols: np.ndarray
    blocks: tuple[tuple[_Block, ...], ...]  # [orientation][index in scales]

    @property
    def max_box(self) -> tuple[int, int]:
        return (max(b.values.shape[0] for bs in self.blocks for b in bs),
                max(b.values.shape[1] for bs in self.blocks for b in bs))


def _crop_indices(full: int, n: int) -> np.ndarray:
    """FFT-order indices of the n frequencies nearest DC out of ``full`` (n even or n = full)."""
    return np.arange(full) if n >= full else np.r_[0 : n // 2, full - n // 2 : full]


def _circular_span(occupied: np.ndarray) -> tuple[int, int]:
    """(start, length) of the shortest circular interval holding every True of a 1-D mask."""
    n = len(occupied)
    if occupied.all() or not occupied.any():
        return 0, n
    # The interval is the complement of the longest circular run of False.
    doubled = np.r_[occupied, occupied]
    best_len, best_end, run = 0, 0, 0
    for i, v in enumerate(doubled):
        run = 0 if v else run + 1
        if run > best_len:
            best_len, best_end = run, i
    return (best_end + 1) % n, n - best_len


_NEGLIGIBLE = 1e-6  # bank entries below this fraction of the filter's peak are treated as zero (float32 noise)


def _block(g: np.ndarray) -> _Block:
    support = g > _NEGLIGIBLE * g.max()
    r0, bh = _circular_span(support.any(axis=1))
    c0, bw = _circular_span(support.any(axis=0))
    rows, cols = (r0 + np.arange(bh)) % g.shape[0], (c0 + np.arange(bw)) % g.shape[1]
    box = np.where(support, g, 0)[np.ix_(rows, cols)]
    values = np.repeat(box[..., None], 2, axis=-1).astype(np.float32)
    values.setflags(write=False)
    return _Block(r0, c0, values)


def _even(n: int) -> int:
    while n % 2:
        n = cv2.getOptimalDFTSize(n + 1)
    return n


@lru_cache(maxsize=2)
def _bands(shape: tuple[int, int], cfg: MimConfig) -> tuple[_Band, ...]:
    """The scales grouped by the grid they are transformed on, largest grid first. The filter values carry the
    1/(H W) of the full-size inverse DFT, so every grid returns the full-size response at its samples."""
    full_bank = filter_bank(shape, cfg) / np.float32(shape[0] * shape[1])
    sizes: dict[tuple[int, int], list[int]] = {}
    for s in range(cfg.n_scales):
        r = band_radius(s, cfg)
        size = tuple(min(n, _even(cv2.getOptimalDFTSize(int(np.ceil(2 * r * n))))) for n in shape)
        sizes.setdefault(size, []).append(s)  # type: ignore[arg-type]
    bands = []
    for size, scales in sorted(sizes.items(), key=lambda kv: -kv[0][0] * kv[0][1]):
        rows, cols = _crop_indices(shape[0], size[0]), _crop_indices(shape[1], size[1])
        blocks = tuple(tuple(_block(full_bank[o, s][np.ix_(rows, cols)]) for s in scales)
                       for o in range(cfg.n_orient))
        bands.append(_Band(size, tuple(scales), rows, cols, blocks))
    return tuple(bands)


def fft_shape(image_shape: tuple[int, int], margin: int) -> tuple[int, int]:
    return tuple(cv2.getOptimalDFTSize(n + 2 * margin) for n in image_shape)  # type: ignore[return-value]


def _spectrum(image: np.ndarray, cfg: MimConfig) -> tuple[np.ndarray, tuple[int, int]]:
    h, w = image.shape
    m = cfg.fft_margin_px
    shape = fft_shape((h, w), m)
    padded = np.zeros(shape, dtype=np.float32)
    padded[m : m + h, m : m + w] = image
    return cv2.dft(padded, flags=cv2.DFT_COMPLEX_OUTPUT), shape  # (H, W, 2)


def _grid_map(src: tuple[int, int], dst: tuple[int, int], offset: float = 0.0) -> np.ndarray:
    """Inverse affine map for warpAffine: pixel (r, c) of a grid sampling the full transform at ``dst`` points
    per side, shifted by ``offset`` full-grid pixels, lies at (r + offset) * ratio on the ``src`` grid."""
    ky, kx = src[0] / dst[0], src[1] / dst[1]
    return np.array([[kx, 0.0, offset * kx], [0.0, ky, offset * ky]])


def orientation_amplitudes(image: np.ndarray, cfg: MimConfig, orientations=None, spectrum=None):
    """Yield (o, A_o) for each orientation: A_o = sum_s |IFFT(F * G_s * S_o)| (H, W) float32, margin cropped.
    The yielded array is reused: consume it before advancing."""
    h, w = image.shape
    m = cfg.fft_margin_px
    if spectrum is None:
        spectrum, shape = _spectrum(image, cfg)
    else:
        shape = spectrum.shape[:2]
    bands = _bands(shape, cfg)
    # Every buffer is allocated once per call and written in place: fresh 1.5 MB temporaries per transform cost
    # more in page faults than the transform itself (measured: magnitude 0.45 ms -> 0.13 ms per filter).
    work = []
    for band in bands:
        full = band.size == shape
        sub = spectrum if full else spectrum[band.rows][:, band.cols]
        bh, bw = band.max_box
        wrapped = cv2.copyMakeBorder(sub, 0, bh, 0, bw, cv2.BORDER_WRAP)  # boxes that wrap are plain slices
        product = np.zeros(band.size + (2,), dtype=np.float32)  # zero outside the current box
        crop = (h, w) if full else band.size
        work.append((band, full, wrapped, product, np.empty_like(product),
                     [np.empty(crop, dtype=np.float32) for _ in range(3)]))
    coarse = [band for band, full, *_ in work if not full]
    coarse_acc = [np.empty(b.size, dtype=np.float32) for b in coarse]
    resampled = np.empty(coarse[0].size if coarse else (1, 1), dtype=np.float32)
    acc, image_acc = np.empty((h, w), dtype=np.float32), np.empty((h, w), dtype=np.float32)
    for o in range(cfg.n_orient) if orientations is None else orientations:
        acc.fill(0.0)
        for k, (band, full, wrapped, product, response, (re, im, mag)) in enumerate(work):
            target = acc if full else coarse_acc[k - (len(work) - len(coarse))]
            target.fill(0.0)
            for blk in band.blocks[o]:
                bh, bw = blk.values.shape[:2]
                box = product[:bh, :bw]
                cv2.multiply(wrapped[blk.r0 : blk.r0 + bh, blk.c0 : blk.c0 + bw], blk.values, dst=box)
                cv2.idft(product, dst=response, flags=cv2.DFT_COMPLEX_OUTPUT)
                box.fill(0.0)
                cv2.split(response[m : m + h, m : m + w] if full else response, [re, im])  # image, not margin
                cv2.magnitude(re, im, mag)
                cv2.add(target, mag, dst=target)
        if coarse:  # the coarse grids' amplitudes onto the largest coarse grid, then once onto the image
            first = coarse_acc[0]
            for band, band_acc in zip(coarse[1:], coarse_acc[1:]):
                cv2.warpAffine(band_acc, _grid_map(band.size, coarse[0].size), first.shape[::-1], dst=resampled,
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_WRAP)
                cv2.add(first, resampled, dst=first)
            cv2.warpAffine(first, _grid_map(coarse[0].size, shape, m), (w, h), dst=image_acc,
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_WRAP)
            cv2.add(acc, image_acc, dst=acc)
        yield o, acc


def _running_max(pairs, shape) -> tuple[np.ndarray, np.ndarray]:
    """Arg-max (1-based index) and max over a sequence of (index, map); the earliest index wins ties."""
    max_amp = np.full(shape, -1.0, dtype=np.float32)
    idx = np.zeros(shape, dtype=np.uint8)
    label = np.empty(shape, dtype=np.uint8)
    for o, amp in pairs:
        label.fill(o + 1)
        cv2.copyTo(label, cv2.compare(amp, max_amp, cv2.CMP_GT), idx)
        cv2.max(max_amp, amp, dst=max_amp)
    return idx, max_amp


def maximum_index_map(image: np.ndarray, cfg: MimConfig | None = None):
    """BV image (uint8 or float, 0..255) -> (MIM uint8 in 0..No, max amplitude float32), both image-sized.
    The arg-max over orientations is kept incrementally (the first orientation wins ties); with cfg.threads > 1
    contiguous groups of orientations run in parallel and are merged in order (the same result)."""
    cfg = cfg or MimConfig()
    image = np.asarray(image, dtype=np.float32)
    spectrum, _ = _spectrum(image, cfg)
    groups = [g for g in np.array_split(np.arange(cfg.n_orient), cfg.threads) if len(g)]

    def run(group):
        return _running_max(orientation_amplitudes(image, cfg, group, spectrum), image.shape)

    parts = run_parts(run, groups)
    mim, max_amp = parts[0]
    for part_mim, part_max in parts[1:]:
        cv2.copyTo(part_mim, cv2.compare(part_max, max_amp, cv2.CMP_GT), mim)
        cv2.max(max_amp, part_max, dst=max_amp)
    mim[max_amp <= cfg.min_amplitude] = 0
    return mim, max_amp
