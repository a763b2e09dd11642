"""Vectorised ray caster for a world of textured rectangles, and the camera's photometric model.

A numba row tracer (run in parallel over image rows) casts the ray of every pixel against the quads whose screen
bounding box covers it, keeps the nearest hit, and shades it: trilinear (mip-mapped, level chosen by the
pixel's footprint on the surface) texture lookup × (ambient + sun + point lights, Lambertian, no
shadows).  Rays follow the project's pinhole model exactly: pixel (i, j) looks along optical direction
((i − cx)/fx, (j − cy)/fy, 1), so a world point lands where `StereoCalibration.project` puts it and the
depth map holds Z in the camera optical frame.

The photometric stage turns radiance into uint8 like a sensor would: exposure × gain, black offset,
vignetting, read + shot noise, quantisation.  The two cameras get different gain and offset.  For a
stereo frame both views are traced and exposed in one parallel pass (`Renderer.stereo`); motion blur
uses the float radiance path (`Renderer.radiance` with accumulation, then `Renderer.expose`).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from common.sim.world import DECAL_BIAS_M, World

NEAR_M = 0.01


@nb.njit(cache=True, error_model="numpy")
def _screen_bboxes(cam_c, R_cw, fx, fy, cx, cy, W, H, origin, u, v):
    """(Q, 4) int64 [u0, u1, v0, v1] pixel bounds of each quad after clipping at the near plane
    (u0 > u1 when the quad is not visible at all) and (Q,) its nearest optical Z.  R_cw rotates map
    vectors into the optical frame."""
    Q = origin.shape[0]
    out = np.empty((Q, 4), np.int64)
    zmin = np.full(Q, np.inf)
    poly = np.empty((4, 3))
    clipped = np.empty((8, 3))
    for q in range(Q):
        for k in range(4):
            p = origin[q].copy()
            if k == 1 or k == 2:
                p += u[q]
            if k == 2 or k == 3:
                p += v[q]
            d = p - cam_c
            for r in range(3):
                poly[k, r] = R_cw[r, 0] * d[0] + R_cw[r, 1] * d[1] + R_cw[r, 2] * d[2]
        n = 0  # Sutherland–Hodgman against z >= NEAR_M
        for k in range(4):
            a = poly[k]
            b = poly[(k + 1) % 4]
            ina = a[2] >= NEAR_M
            inb = b[2] >= NEAR_M
            if ina:
                clipped[n] = a
                n += 1
            if ina != inb:
                t = (NEAR_M - a[2]) / (b[2] - a[2])
                clipped[n] = a + t * (b - a)
                n += 1
        if n == 0:
            out[q, 0], out[q, 1], out[q, 2], out[q, 3] = 1, 0, 1, 0
            continue
        umin, umax, vmin, vmax = 1e18, -1e18, 1e18, -1e18
        for k in range(n):
            zmin[q] = min(zmin[q], clipped[k, 2])
            pu = fx * clipped[k, 0] / clipped[k, 2] + cx
            pv = fy * clipped[k, 1] / clipped[k, 2] + cy
            umin, umax = min(umin, pu), max(umax, pu)
            vmin, vmax = min(vmin, pv), max(vmax, pv)
        out[q, 0] = max(0, int(np.floor(umin)) - 1)
        out[q, 1] = min(W - 1, int(np.ceil(umax)) + 1)
        out[q, 2] = max(0, int(np.floor(vmin)) - 1)
        out[q, 3] = min(H - 1, int(np.ceil(vmax)) + 1)
        if out[q, 0] > out[q, 1] or out[q, 2] > out[q, 3]:
            out[q, 0], out[q, 1], out[q, 2], out[q, 3] = 1, 0, 1, 0
    return out, zmin


@nb.njit(cache=True, error_model="numpy")
def _fast_log2(x):
    """log2 of x > 0 to within 0.01 (mip selection does not need more), much cheaper than np.log2."""
    m, e = math.frexp(x)           # x = m · 2^e, m in [0.5, 1)
    y = 2.0 * m - 1.0              # log2(1 + y), y in [0, 1)
    return (e - 1) + y * (1.3465 - 0.3465 * y)


@nb.njit(cache=True, error_model="numpy")
def _bilinear(texels, off, w, h, x, y, wrap, weight):
    """weight × bilinear sample (r, g, b) of one mip level at texel coordinates (x, y)."""
    x -= 0.5
    y -= 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    ix0 = int(x0)
    iy0 = int(y0)
    ix1 = ix0 + 1
    iy1 = iy0 + 1
    if wrap:  # texture sizes are powers of two: masking wraps negatives too
        ix0 &= w - 1
        ix1 &= w - 1
        iy0 &= h - 1
        iy1 &= h - 1
    else:
        ix0 = min(max(ix0, 0), w - 1)
        ix1 = min(max(ix1, 0), w - 1)
        iy0 = min(max(iy0, 0), h - 1)
        iy1 = min(max(iy1, 0), h - 1)
    i00 = off + iy0 * w + ix0
    i01 = off + iy0 * w + ix1
    i10 = off + iy1 * w + ix0
    i11 = off + iy1 * w + ix1
    w00 = np.float32((1 - fx) * (1 - fy) * weight)  # float32 weights: no per-texel conversions
    w01 = np.float32(fx * (1 - fy) * weight)
    w10 = np.float32((1 - fx) * fy * weight)
    w11 = np.float32(fx * fy * weight)
    r = texels[i00, 0] * w00 + texels[i01, 0] * w01 + texels[i10, 0] * w10 + texels[i11, 0] * w11
    g = texels[i00, 1] * w00 + texels[i01, 1] * w01 + texels[i10, 1] * w10 + texels[i11, 1] * w11
    b = texels[i00, 2] * w00 + texels[i01, 2] * w01 + texels[i10, 2] * w10 + texels[i11, 2] * w11
    return r, g, b


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def _plane_offsets(cam_c, origin, normal):
    """(Q,) (origin − camera)·normal: the numerator of every ray-plane intersection of this view."""
    Q = origin.shape[0]
    on = np.empty(Q)
    for q in range(Q):
        on[q] = ((origin[q, 0] - cam_c[0]) * normal[q, 0] + (origin[q, 1] - cam_c[1]) * normal[q, 1]
                 + (origin[q, 2] - cam_c[2]) * normal[q, 2])
    return on


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def _trace_row(j, cam_c, R_wc, on, fx, fy, cx, cy, W, bbox, order, n_order, zmin,
               origin, normal, u_dual, v_dual, tex, decal, tex_scale, tiles, texel_density,
               texels, toff, tw, th, nlev, emissive,
               ambient, sun, sun_int, lights, sky, decal_bias, row_rad, row_depth):
    """Radiance (W, 3) and depth (W,) of image row j: nearest hit of each pixel's ray, shaded."""
    inv_fx = 1.0 / fx
    inv_fy = 1.0 / fy
    # Quads whose screen box covers this row, nearest first (``order`` is sorted by zmin).
    rowq = np.empty(max(n_order, 1), np.int64)
    nq = 0
    for k in range(n_order):
        q = order[k]
        if bbox[q, 2] <= j and j <= bbox[q, 3]:
            rowq[nq] = q
            nq += 1
    prev = -1
    oy = (j - cy) * inv_fy
    for i in range(W):
        ox = (i - cx) * inv_fx
        dx = R_wc[0, 0] * ox + R_wc[0, 1] * oy + R_wc[0, 2]
        dy = R_wc[1, 0] * ox + R_wc[1, 1] * oy + R_wc[1, 2]
        dz = R_wc[2, 0] * ox + R_wc[2, 1] * oy + R_wc[2, 2]
        best = np.inf
        bq = -1
        bt = 0.0
        ba = 0.0
        bb = 0.0
        bden = 0.0
        for k in range(-1, nq):
            # The previous pixel's quad first: it usually wins, so the rest fail the depth test early.
            if k < 0:
                q = prev
                if q < 0:
                    continue
            else:
                q = rowq[k]
                if zmin[q] - decal_bias > best:
                    break
                if q == prev:
                    continue
            if i < bbox[q, 0] or i > bbox[q, 1]:
                continue
            den = dx * normal[q, 0] + dy * normal[q, 1] + dz * normal[q, 2]
            if den > -1e-12 and den < 1e-12:
                continue
            if decal[q] and den >= 0:
                continue
            t = on[q] / den
            if t <= 1e-6:
                continue
            te = t - decal_bias if decal[q] else t
            if te >= best:
                continue
            px = cam_c[0] + t * dx - origin[q, 0]
            py = cam_c[1] + t * dy - origin[q, 1]
            pz = cam_c[2] + t * dz - origin[q, 2]
            a = px * u_dual[q, 0] + py * u_dual[q, 1] + pz * u_dual[q, 2]
            if a < 0.0 or a > 1.0:
                continue
            b = px * v_dual[q, 0] + py * v_dual[q, 1] + pz * v_dual[q, 2]
            if b < 0.0 or b > 1.0:
                continue
            best = te
            bq = q
            bt = t
            ba = a
            bb = b
            bden = den
        prev = bq
        dn = np.sqrt(dx * dx + dy * dy + dz * dz)
        if bq < 0:
            elev = dz / dn
            f = 1.0 - 0.35 * max(elev, 0.0)
            for ch in range(3):
                row_rad[i, ch] = sky[ch] * f
            row_depth[i] = np.inf
            continue
        row_depth[i] = bt
        tid = tex[bq]
        s = ba * tex_scale[bq, 0]
        tt = bb * tex_scale[bq, 1]
        wrap = tiles[bq]
        # Mip level = log2 of the pixel footprint in texels: distance·density/fx, widened by
        # 1/sqrt(cos incidence) (geometric mean of the along- and across-slant footprints).
        # Squared to avoid a square root: lod = ½·log2(t²·dn³·(density/fx)² / max(|d·n|, 0.02·dn)).
        cden = max(abs(bden), 0.02 * dn)
        x2 = bt * bt * dn * dn * dn * texel_density[bq] * texel_density[bq] * inv_fx * inv_fx / cden
        lod = 0.5 * _fast_log2(max(x2, 1.0))
        maxl = nlev[tid] - 1
        if lod > maxl:
            lod = float(maxl)
        l0 = int(lod)
        # "Brilinear": a single bilinear level except in the middle 30 % between two levels, where
        # the two are blended (saves most second-level fetches, no visible level seams).
        fr = min(max((lod - l0 - 0.35) * (1.0 / 0.3), 0.0), 1.0)
        l1 = min(l0 + 1, maxl)
        # Shading: facing normal towards the camera.
        sg = -1.0 if bden > 0 else 1.0
        nx = normal[bq, 0] * sg
        ny = normal[bq, 1] * sg
        nz = normal[bq, 2] * sg
        if emissive[tid]:
            shade = 1.3
        else:
            shade = ambient + sun_int * max(0.0, nx * sun[0] + ny * sun[1] + nz * sun[2])
            hx = cam_c[0] + bt * dx
            hy = cam_c[1] + bt * dy
            hz = cam_c[2] + bt * dz
            for li in range(lights.shape[0]):
                lx = lights[li, 0] - hx
                ly = lights[li, 1] - hy
                lz = lights[li, 2] - hz
                d2 = lx * lx + ly * ly + lz * lz
                ndl = (nx * lx + ny * ly + nz * lz) / np.sqrt(d2 + 1e-12)
                if ndl > 0:
                    shade += lights[li, 3] * ndl / (1.0 + d2 / (lights[li, 4] * lights[li, 4]))
        w0 = tw[tid, l0]
        h0 = th[tid, l0]
        if 0.0 < fr < 1.0 and l1 != l0:
            r0, g0, b0 = _bilinear(texels, toff[tid, l0], w0, h0, s * w0, (1.0 - tt) * h0, wrap, 1.0 - fr)
            w1 = tw[tid, l1]
            h1 = th[tid, l1]
            r1, g1, b1 = _bilinear(texels, toff[tid, l1], w1, h1, s * w1, (1.0 - tt) * h1, wrap, fr)
            r0 += r1
            g0 += g1
            b0 += b1
        else:
            lv = l1 if fr >= 1.0 else l0
            w0 = tw[tid, lv]
            h0 = th[tid, lv]
            r0, g0, b0 = _bilinear(texels, toff[tid, lv], w0, h0, s * w0, (1.0 - tt) * h0, wrap, 1.0)
        row_rad[i, 0] = r0 * shade
        row_rad[i, 1] = g0 * shade
        row_rad[i, 2] = b0 * shade


@nb.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _cast(cam_c, R_wc, fx, fy, cx, cy, W, H, bbox, order, zmin,
          origin, normal, u_dual, v_dual, tex, decal, tex_scale, tiles, texel_density,
          texels, toff, tw, th, nlev, emissive,
          ambient, sun, sun_int, lights, sky, decal_bias,
          out_rad, out_depth, accumulate):
    """Radiance and depth of one view (radiance added to ``out_rad`` when ``accumulate``)."""
    on = _plane_offsets(cam_c, origin, normal)
    for j in nb.prange(H):
        row_rad = np.empty((W, 3), np.float32)
        row_depth = np.empty(W, np.float32)
        _trace_row(j, cam_c, R_wc, on, fx, fy, cx, cy, W, bbox, order, order.shape[0], zmin,
                   origin, normal, u_dual, v_dual, tex, decal, tex_scale, tiles, texel_density,
                   texels, toff, tw, th, nlev, emissive,
                   ambient, sun, sun_int, lights, sky, decal_bias, row_rad, row_depth)
        if accumulate:
            for i in range(W):
                for ch in range(3):
                    out_rad[j, i, ch] += row_rad[i, ch]
        else:
            out_rad[j] = row_rad
            out_depth[j] = row_depth


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def _expose_row(row_rad, j, g0, offset, vignette, table, start, stride, read_noise, shot_noise, out_row):
    """Sensor model for one row: gain × vignetting, black offset, read + shot noise, rounding.  The
    noise of value k (pixel-major, channel-minor) is table[(start + k·stride) mod N] with an odd stride,
    a permutation of the table: every image gets its own pattern, independent of thread scheduling."""
    W = row_rad.shape[0]
    mask = table.shape[0] - 1
    for i in range(W):
        g = g0 * vignette[j, i] * 255.0
        k0 = (j * W + i) * 3
        for ch in range(3):
            val = row_rad[i, ch] * g + offset
            sig = np.sqrt(read_noise * read_noise + shot_noise * max(val, 0.0))
            val += sig * table[(start + (k0 + ch) * stride) & mask]
            val = np.floor(val + 0.5)
            out_row[i, ch] = np.uint8(min(max(val, 0.0), 255.0))


@nb.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _sensor(rad, scale, gain, offset, vignette, table, start, stride, read_noise, shot_noise, out):
    """uint8 image of a whole radiance image (see _expose_row)."""
    H = rad.shape[0]
    for j in nb.prange(H):
        _expose_row(rad[j], j, scale * gain, offset, vignette, table, start, stride, read_noise, shot_noise,
                    out[j])


@nb.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _cast_stereo(cams_c, cams_R, fx, fy, cx, cy, W, H, bbox, order, n_order, zmin,
                 origin, normal, u_dual, v_dual, tex, decal, tex_scale, tiles, texel_density,
                 texels, toff, tw, th, nlev, emissive,
                 ambient, sun, sun_int, lights, sky, decal_bias,
                 gains, offsets, vignette, table, starts, strides, read_noise, shot_noise,
                 out_images, out_depth):
    """Both views of a rig traced and exposed in one parallel pass (rows of the two cameras
    interleaved): uint8 images (2, H, W, 3) and the first camera's depth (H, W)."""
    on0 = _plane_offsets(cams_c[0], origin, normal)
    on1 = _plane_offsets(cams_c[1], origin, normal)
    for jj in nb.prange(2 * H):
        cam = jj % 2
        j = jj // 2
        on = on0 if cam == 0 else on1
        row_rad = np.empty((W, 3), np.float32)
        row_depth = np.empty(W, np.float32)
        _trace_row(j, cams_c[cam], cams_R[cam], on, fx, fy, cx, cy, W, bbox[cam], order[cam], n_order[cam],
                   zmin[cam], origin, normal, u_dual, v_dual, tex, decal, tex_scale, tiles, texel_density,
                   texels, toff, tw, th, nlev, emissive,
                   ambient, sun, sun_int, lights, sky, decal_bias, row_rad, row_depth)
        if cam == 0:
            out_depth[j] = row_depth
        _expose_row(row_rad, j, gains[cam], offsets[cam], vignette, table, starts[cam], strides[cam],
                    read_noise, shot_noise, out_images[cam, j])


NOISE_TABLE_BITS = 20


def noise_table(seed: int) -> np.ndarray:
    """2^20 standard-normal float32 values; each image reads them in a fresh odd-stride order."""
    return np.random.default_rng([int(seed), 0x0153]).standard_normal(1 << NOISE_TABLE_BITS, dtype=np.float32)


class Renderer:
    """Renders one pinhole camera view of a World (radiance and depth), and applies sensor photometry."""

    def __init__(self, world: World, width: int, height: int, fx: float, fy: float, cx: float, cy: float):
        self.world = world
        self.W, self.H = int(width), int(height)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)
        lt = world.scenario.lighting
        sun = np.asarray(lt.sun, float)
        self._sun = sun / max(np.linalg.norm(sun), 1e-12)
        self._lights = np.array([[*l.position, l.intensity, l.radius] for l in lt.lights], float).reshape(-1, 5)
        self._sky = np.asarray(lt.sky_color, float) / 255.0
        yy, xx = np.mgrid[0:self.H, 0:self.W]
        r2 = ((xx - self.cx) / (self.W / 2)) ** 2 + ((yy - self.cy) / (self.H / 2)) ** 2
        self.vignette_strength = 0.0
        self._r2 = (r2 / 2.0).astype(np.float32)  # 1 at the corners

    def vignette(self, strength: float) -> np.ndarray:
        return (1.0 - strength * self._r2).astype(np.float32)

    def radiance(self, T_map_optical: np.ndarray, out_rad=None, out_depth=None, accumulate=False):
        """(H, W, 3) float32 radiance and (H, W) float32 depth (Z, inf for sky) seen from a camera pose."""
        q, a = self.world.quads, self.world.atlas
        if out_rad is None:
            out_rad = np.empty((self.H, self.W, 3), np.float32)
        if out_depth is None:
            out_depth = np.empty((self.H, self.W), np.float32)
        c, R_wc, bbox, order, zmin = self._view_setup(T_map_optical)
        _cast(c, R_wc, self.fx, self.fy, self.cx, self.cy, self.W, self.H, bbox, order, zmin,
              q.origin, q.normal, q.u_dual, q.v_dual, q.tex, q.decal, q.tex_scale, q.tiles, q.texel_density,
              a.texels, a.offset, a.width, a.height, a.n_levels, a.emissive,
              float(self.world.scenario.lighting.ambient), self._sun,
              float(self.world.scenario.lighting.sun_intensity), self._lights, self._sky, DECAL_BIAS_M,
              out_rad, out_depth, accumulate)
        return out_rad, out_depth

    def _view_setup(self, T_map_optical: np.ndarray):
        q = self.world.quads
        c = np.ascontiguousarray(T_map_optical[:3, 3], float)
        R_wc = np.ascontiguousarray(T_map_optical[:3, :3], float)
        bbox, zmin = _screen_bboxes(c, np.ascontiguousarray(R_wc.T), self.fx, self.fy, self.cx, self.cy,
                                    self.W, self.H, q.origin, q.u, q.v)
        visible = np.flatnonzero(bbox[:, 0] <= bbox[:, 1])
        order = visible[np.argsort(zmin[visible], kind="stable")]
        return c, R_wc, bbox, order, zmin

    def stereo(self, T_map_left: np.ndarray, T_map_right: np.ndarray, gains, offsets, vignette: np.ndarray,
               table: np.ndarray, rng: np.random.Generator, read_noise: float, shot_noise: float):
        """(left, right) uint8 images and the left depth (H, W) float32, traced and exposed in one
        parallel pass — the fast path of a stereo frame (no motion blur)."""
        q, a = self.world.quads, self.world.atlas
        views = [self._view_setup(T_map_left), self._view_setup(T_map_right)]
        Q = len(q)
        order = np.zeros((2, max(Q, 1)), np.int64)
        n_order = np.zeros(2, np.int64)
        for k, v in enumerate(views):
            order[k, :len(v[3])] = v[3]
            n_order[k] = len(v[3])
        starts, strides = self._noise_draws(table, rng, 2)
        images = np.empty((2, self.H, self.W, 3), np.uint8)
        depth = np.empty((self.H, self.W), np.float32)
        lt = self.world.scenario.lighting
        _cast_stereo(np.stack([views[0][0], views[1][0]]), np.stack([views[0][1], views[1][1]]),
                     self.fx, self.fy, self.cx, self.cy, self.W, self.H,
                     np.stack([views[0][2], views[1][2]]), order, n_order, np.stack([views[0][4], views[1][4]]),
                     q.origin, q.normal, q.u_dual, q.v_dual, q.tex, q.decal, q.tex_scale, q.tiles, q.texel_density,
                     a.texels, a.offset, a.width, a.height, a.n_levels, a.emissive,
                     float(lt.ambient), self._sun, float(lt.sun_intensity), self._lights, self._sky, DECAL_BIAS_M,
                     np.asarray(gains, float), np.asarray(offsets, float), vignette, table, starts, strides,
                     float(read_noise), float(shot_noise), images, depth)
        return images[0], images[1], depth

    @staticmethod
    def _noise_draws(table: np.ndarray, rng: np.random.Generator, n_images: int):
        n = table.shape[0]
        if n & (n - 1):
            raise ValueError("noise table length must be a power of two")
        starts = np.empty(n_images, np.int64)
        strides = np.empty(n_images, np.int64)
        for k in range(n_images):
            starts[k] = int(rng.integers(0, n))
            strides[k] = int(rng.integers(0, 128)) * 2 + 1  # odd: a permutation; small: cache-friendly
        return starts, strides

    @staticmethod
    def expose(rad: np.ndarray, scale: float, gain: float, offset: float, vignette: np.ndarray,
               table: np.ndarray, rng: np.random.Generator, read_noise: float, shot_noise: float) -> np.ndarray:
        """uint8 image of a radiance image through the sensor model (gain, black offset, vignetting,
        read + shot noise drawn from ``table`` in an order chosen by ``rng``, rounding)."""
        out = np.empty(rad.shape, np.uint8)
        starts, strides = Renderer._noise_draws(table, rng, 1)
        _sensor(rad, float(scale), float(gain), float(offset), vignette, table, int(starts[0]), int(strides[0]),
                float(read_noise), float(shot_noise), out)
        return out
