"""Numba passes of the path tracer's shading and sampling on the CPU.

`shade_and_sample` fuses one bounce's work after the closest-hit query: escaped rays (environment,
MIS), shading geometry, emission at hits (MIS), first-hit AOVs, next-event estimation (one light
sample and its shadow ray, MIS), BSDF sampling and Russian roulette, and the compaction of the
shadow rays and the surviving paths. `add_unoccluded` adds the contributions of the shadow rays
that reached their light. `camera_rays` and `film_add` are the wavefront's first and last steps.
They replace the chains of small whole-batch torch ops of `shading_stages.TorchShadingStages`
(each op a pass over memory with its own dispatch cost).

They compute what the torch stages compute (the formulas of `materials.py`, `lights.py` and
`sampling.py`, the same random numbers in the same roles), mostly in float64 arithmetic on float32
inputs, so answers agree with the torch path to float tolerance (tests compare them). Tables are
tuples of arrays built once per scene (`shading_stages.NumbaShadingStages`), unpacked once per pass.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["shade_and_sample", "add_unoccluded", "camera_rays", "film_add", "bsdf_sample_rows", "bsdf_eval_rows", "light_sample_rows", "environment_rows"]

_DIFFUSE, _CONDUCTOR, _PLASTIC, _EMISSIVE = 0, 1, 2, 3  # MaterialKind
_AREA, _POINT, _ENVIRONMENT = 0, 1, 2  # light kinds, in LightSet.kinds order
_MIN_COAT_PROBABILITY = 0.25
SHADOW_T_MAX = 1.0 - 1e-3  # shadow rays (direction = light point - origin) stop at this t
# Secondary rays leave a hit at least this much of its largest coordinate off the surface (4-8
# float32 ulps of the point): far from the origin the instance's own offset (1e-4 of its size) is
# below the point's rounding, and surfaces shadowed themselves (acne: a unit mesh at x = 1e4 lost
# 5% of its brightness). As pbrt bounds a hit point's error by a few ulps of its coordinates.
POSITION_OFFSET = 2.0 ** -21
_INV_PI = 1.0 / math.pi

_jit = numba.njit(cache=True, inline="always", error_model="numpy")  # numba-level inlining: measured 35% faster kernels (compiles ~10 s longer, once: cached)


# --- small vector helpers -----------------------------------------------------------------------


@_jit
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@_jit
def _normalize(x, y, z):
    """torch.nn.functional.normalize: divide by max(norm, 1e-12)."""
    n = max(math.sqrt(x * x + y * y + z * z), 1e-12)
    return x / n, y / n, z / n


@_jit
def _normalize32(x, y, z):
    n = max(np.float32(math.sqrt(x * x + y * y + z * z)), np.float32(1e-12))
    return x / n, y / n, z / n


@_jit
def _luminance(r, g, b):
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


@_jit
def _power_heuristic(a, b):
    a2, b2 = a * a, b * b
    d = a2 + b2
    return a2 / d if d > 0 else 0.0


@_jit
def _basis(nx, ny, nz):
    """Duff et al. 2017 (as `sampling.orthonormal_basis`): tangent, bitangent."""
    sign = 1.0 if nz >= 0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return (1.0 + sign * nx * nx * a, sign * b, -sign * nx), (b, sign + ny * ny * a, -ny)


@_jit
def _search(cdf, u):
    """`DiscreteDistribution.sample`: first index with cdf > u (searchsorted right), clamped."""
    i = np.searchsorted(cdf, u, side="right")
    return min(i, cdf.shape[0] - 1)


# --- materials (local frame, z = normal) -----------------------------------------------------------


@_jit
def _fresnel_dielectric(cos_i, eta):
    cos_i = min(max(cos_i, 0.0), 1.0)
    sin_t2 = (1.0 - cos_i * cos_i) / (eta * eta)
    if sin_t2 >= 1.0:
        return 1.0
    cos_t = math.sqrt(max(1.0 - sin_t2, 0.0))
    rs = (cos_i - eta * cos_t) / max(cos_i + eta * cos_t, 1e-12)
    rp = (eta * cos_i - cos_t) / max(eta * cos_i + cos_t, 1e-12)
    return 0.5 * (rs * rs + rp * rp)


@_jit
def _ggx_d(cos_h, alpha):
    if cos_h <= 0:
        return 0.0
    a2 = alpha * alpha
    denom = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * denom * denom)


@_jit
def _ggx_lambda(x, y, z, alpha):
    z2 = max(z * z, 1e-12)
    tan2 = (x * x + y * y) / z2
    return 0.5 * (math.sqrt(1.0 + alpha * alpha * tan2) - 1.0)


@_jit
def _coat_probability(kind, ior, ar, ag, ab, cos_o):
    if kind == _CONDUCTOR:
        return 1.0
    if kind != _PLASTIC:
        return 0.0
    fo = _fresnel_dielectric(max(cos_o, 0.0), ior)
    kd = (1.0 - fo) * _luminance(ar, ag, ab)
    return min(max(fo / max(fo + kd, 1e-8), _MIN_COAT_PROBABILITY), 1.0)


@_jit
def lobes(kind, alpha, ior, ar, ag, ab, lox, loy, loz, lix, liy, liz):
    """`MaterialTable._lobes` for one row: (f*cos r, g, b, pdf)."""
    cos_o, cos_i = loz, liz
    if not (cos_o > 0 and cos_i > 0):
        return 0.0, 0.0, 0.0, 0.0
    if kind == _DIFFUSE or kind == _EMISSIVE:
        c = cos_i * _INV_PI
        return ar * c, ag * c, ab * c, c
    hx, hy, hz = _normalize(lox + lix, loy + liy, loz + liz)
    o_dot_h = max(_dot(lox, loy, loz, hx, hy, hz), 0.0)
    d = _ggx_d(hz, alpha)
    g2 = 1.0 / (1.0 + _ggx_lambda(lox, loy, loz, alpha) + _ggx_lambda(lix, liy, liz, alpha))
    safe_cos_o = max(cos_o, 1e-8)
    micro = d * g2 / (4.0 * safe_cos_o)
    if kind == _CONDUCTOR:
        s5 = (1.0 - min(max(o_dot_h, 0.0), 1.0)) ** 5
        vr = (ar + (1.0 - ar) * s5) * micro
        vg = (ag + (1.0 - ag) * s5) * micro
        vb = (ab + (1.0 - ab) * s5) * micro
    else:
        spec = _fresnel_dielectric(o_dot_h, ior) * micro
        transmit = (1.0 - _fresnel_dielectric(cos_i, ior)) * (1.0 - _fresnel_dielectric(cos_o, ior))
        base = transmit * cos_i * _INV_PI
        vr, vg, vb = spec + ar * base, spec + ag * base, spec + ab * base
    p_coat = _coat_probability(kind, ior, ar, ag, ab, cos_o)
    pdf_spec = d / ((1.0 + _ggx_lambda(lox, loy, loz, alpha)) * 4.0 * safe_cos_o)
    pdf = p_coat * pdf_spec + (1.0 - p_coat) * cos_i * _INV_PI
    return vr, vg, vb, pdf


@_jit
def _ggx_visible_normal(ox, oy, oz, alpha, u0, u1):
    """Heitz 2018, as `materials.ggx_sample_visible_normal`."""
    vx, vy, vz = _normalize(alpha * ox, alpha * oy, max(oz, 1e-6))
    lensq = vx * vx + vy * vy
    if lensq > 0:
        inv = 1.0 / math.sqrt(max(lensq, 1e-20))
        t1x, t1y, t1z = -vy * inv, vx * inv, 0.0
    else:
        t1x, t1y, t1z = 1.0, 0.0, 0.0
    t2x, t2y, t2z = vy * t1z - vz * t1y, vz * t1x - vx * t1z, vx * t1y - vy * t1x
    r = math.sqrt(u0)
    phi = 2.0 * math.pi * u1
    p1 = r * math.cos(phi)
    p2 = r * math.sin(phi)
    s = 0.5 * (1.0 + vz)
    p2 = (1.0 - s) * math.sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2
    pz = math.sqrt(max(1.0 - p1 * p1 - p2 * p2, 0.0))
    nx = p1 * t1x + p2 * t2x + pz * vx
    ny = p1 * t1y + p2 * t2y + pz * vy
    nz = p1 * t1z + p2 * t2z + pz * vz
    return _normalize(alpha * nx, alpha * ny, max(nz, 1e-6))


@_jit
def _cosine_hemisphere(u0, u1):
    """Concentric disk lifted to the hemisphere (`sampling.cosine_hemisphere`)."""
    ax, ay = 2.0 * u0 - 1.0, 2.0 * u1 - 1.0
    first = abs(ax) > abs(ay)
    r = ax if first else ay
    safe = 1.0 if r == 0 else r
    phi = (math.pi / 4) * (ay / safe) if first else math.pi / 2 - (math.pi / 4) * (ax / safe)
    dx, dy = r * math.cos(phi), r * math.sin(phi)
    return dx, dy, math.sqrt(max(1.0 - (dx * dx + dy * dy), 0.0))


@_jit
def sample_bsdf(kind, alpha, ior, ar, ag, ab, nx, ny, nz, wox, woy, woz, u_lobe, u0, u1):
    """`MaterialTable.sample` for one row: (wi xyz, weight rgb, pdf)."""
    (tx, ty, tz), (bx, by, bz) = _basis(nx, ny, nz)
    lox, loy, loz = _dot(wox, woy, woz, tx, ty, tz), _dot(wox, woy, woz, bx, by, bz), _dot(wox, woy, woz, nx, ny, nz)
    lix, liy, liz = _cosine_hemisphere(u0, u1)
    if kind == _CONDUCTOR or kind == _PLASTIC:
        p_coat = _coat_probability(kind, ior, ar, ag, ab, loz)
        if u_lobe < p_coat:  # mirror wo about a visible microfacet normal
            hx, hy, hz = _ggx_visible_normal(lox, loy, loz, alpha, u0, u1)
            c = 2.0 * _dot(lox, loy, loz, hx, hy, hz)
            lix, liy, liz = c * hx - lox, c * hy - loy, c * hz - loz
        lix, liy, liz = _normalize(lix, liy, liz)
    vr, vg, vb, pdf = lobes(kind, alpha, ior, ar, ag, ab, lox, loy, loz, lix, liy, liz)
    wx = lix * tx + liy * bx + liz * nx
    wy = lix * ty + liy * by + liz * ny
    wz = lix * tz + liy * bz + liz * nz
    if pdf > 0:
        return wx, wy, wz, vr / pdf, vg / pdf, vb / pdf, pdf
    return wx, wy, wz, 0.0, 0.0, 0.0, pdf


@_jit
def _eval_pdf(kind, alpha, ior, ar, ag, ab, nx, ny, nz, wox, woy, woz, wix, wiy, wiz):
    (tx, ty, tz), (bx, by, bz) = _basis(nx, ny, nz)
    return lobes(kind, alpha, ior, ar, ag, ab,
                 _dot(wox, woy, woz, tx, ty, tz), _dot(wox, woy, woz, bx, by, bz), _dot(wox, woy, woz, nx, ny, nz),
                 _dot(wix, wiy, wiz, tx, ty, tz), _dot(wix, wiy, wiz, bx, by, bz), _dot(wix, wiy, wiz, nx, ny, nz))


@_jit
def _texel_bilinear(tex_data, off, w, x0, x1, y0, y1, fx, fy, c):
    """Channel ``c`` of a texture stored row-major from row ``off`` of ``tex_data`` [T, 3]."""
    top = tex_data[off + y0 * w + x0, c] * (1 - fx) + tex_data[off + y0 * w + x1, c] * fx
    bottom = tex_data[off + y1 * w + x0, c] * (1 - fx) + tex_data[off + y1 * w + x1, c] * fx
    return top * (1 - fy) + bottom * fy


@_jit
def _albedo_at(albedo, tex_offset, tex_size, tex_data, mid, u, v, sr, sg, sb):
    """`MaterialTable.albedo_at`: material albedo x bilinear wrapped texture x the surface's colour."""
    r, g, b = float(albedo[mid, 0]), float(albedo[mid, 1]), float(albedo[mid, 2])
    off = tex_offset[mid]
    if off >= 0:
        h, w = tex_size[mid, 0], tex_size[mid, 1]
        x = (u % 1.0) * w - 0.5
        y = (1.0 - (v % 1.0)) * h - 0.5
        x0f, y0f = math.floor(x), math.floor(y)
        fx, fy = x - x0f, y - y0f
        x0, y0 = int(x0f) % w, int(y0f) % h
        x1, y1 = (x0 + 1) % w, (y0 + 1) % h
        r = r * _texel_bilinear(tex_data, off, w, x0, x1, y0, y1, fx, fy, 0)
        g = g * _texel_bilinear(tex_data, off, w, x0, x1, y0, y1, fx, fy, 1)
        b = b * _texel_bilinear(tex_data, off, w, x0, x1, y0, y1, fx, fy, 2)
    return r * sr, g * sg, b * sb


# --- lights ------------------------------------------------------------------------------------------


@_jit
def _to_env(c, s, x, y, z):
    return c * x - s * z, y, s * x + c * z


@_jit
def _direction_to_uv(x, y, z):
    u = (0.5 + math.atan2(x, -z) / (2 * math.pi)) % 1.0
    return u, math.acos(min(max(y, -1.0), 1.0)) / math.pi


@_jit
def _bilinear(image, ya, yb, xa, xb, fx, fy, c):
    """Channel ``c`` of ``image`` [H, W, C] between rows ya/yb and columns xa/xb at fractions fx, fy."""
    top = image[ya, xa, c] * (1 - fx) + image[ya, xb, c] * fx
    bottom = image[yb, xa, c] * (1 - fx) + image[yb, xb, c] * fx
    return top * (1 - fy) + bottom * fy


@_jit
def environment_radiance(color, image, is_constant, c, s, x, y, z):
    """`Environment.radiance` for one unit direction (rotation ``c``, ``s``: cos and sin of rotate_y)."""
    if is_constant:
        return float(color[0]), float(color[1]), float(color[2])
    h, w = image.shape[0], image.shape[1]
    ex, ey, ez = _to_env(c, s, x, y, z)
    u, v = _direction_to_uv(ex, ey, ez)
    fxp = u * w - 0.5
    fyp = v * h - 0.5
    x0f, y0f = math.floor(fxp), math.floor(fyp)
    fx, fy = fxp - x0f, fyp - y0f
    x0, y0 = int(x0f), int(y0f)
    xa, xb = x0 % w, (x0 + 1) % w
    ya, yb = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
    return (_bilinear(image, ya, yb, xa, xb, fx, fy, 0), _bilinear(image, ya, yb, xa, xb, fx, fy, 1),
            _bilinear(image, ya, yb, xa, xb, fx, fy, 2))


@_jit
def environment_pdf(image, pmf, is_constant, c, s, x, y, z):
    """`Environment.pdf` (without the light-kind probability)."""
    if is_constant:
        return 1.0 / (4 * math.pi)
    h, w = image.shape[0], image.shape[1]
    ex, ey, ez = _to_env(c, s, x, y, z)
    u, v = _direction_to_uv(ex, ey, ez)
    px = min(max(int(u * w), 0), w - 1)
    py = min(max(int(v * h), 0), h - 1)
    pdf_uv = pmf[py * w + px] * (h * w)
    sin_theta = math.sqrt(ex * ex + ez * ez)
    if sin_theta > 0:
        return pdf_uv / (2 * math.pi * math.pi * max(sin_theta, 1e-30))
    return 0.0


@_jit
def _area_pdf(normals, density, light, distance, wx, wy, wz):
    """`AreaLights.pdf`: solid-angle density of reaching ``light`` along w at ``distance``."""
    cos_l = -_dot(wx, wy, wz, normals[light, 0], normals[light, 1], normals[light, 2])
    if cos_l > 0:
        return density[light] * distance * distance / max(cos_l, 1e-12)
    return 0.0


@_jit
def _area_light_index(base, holds, lookup, instance, primitive):
    """`AreaLights.light_index` for one hit (-1: not an area light)."""
    if instance < 0 or primitive < 0 or not holds[instance]:
        return -1
    slot = min(base[instance] + primitive, max(lookup.shape[0] - 1, 0))
    return lookup[slot]


@_jit
def sample_light(kinds, a_tris, a_normals, a_emission, a_cdf, a_density, p_positions, p_intensities, p_cdf, p_pmf,
                 e_color, e_image, e_cdf, e_pmf, e_constant, e_cos, e_sin, px, py, pz, u0, u1, u2):
    """`LightSet.sample` for one shading point: (wi xyz, distance, radiance rgb, pdf, is_delta)."""
    k = kinds.shape[0]
    pk = 1.0 / k
    kind_slot = min(int(u0 * k), k - 1)
    u_sel = min(max(u0 * k - kind_slot, 0.0), 1.0 - 1e-7)
    kind = kinds[kind_slot]
    if kind == _AREA:
        tris, emission = a_tris, a_emission
        i = _search(a_cdf, u_sel)
        su = math.sqrt(u1)
        b0 = 1.0 - su
        b1 = u2 * su
        b2 = 1.0 - b0 - b1
        yx = b0 * tris[i, 0, 0] + b1 * tris[i, 1, 0] + b2 * tris[i, 2, 0]
        yy = b0 * tris[i, 0, 1] + b1 * tris[i, 1, 1] + b2 * tris[i, 2, 1]
        yz = b0 * tris[i, 0, 2] + b1 * tris[i, 1, 2] + b2 * tris[i, 2, 2]
        dx, dy, dz = yx - px, yy - py, yz - pz
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        dist = max(norm, 1e-12)
        wx, wy, wz = dx / dist, dy / dist, dz / dist
        pdf = _area_pdf(a_normals, a_density, i, dist, wx, wy, wz) * pk
        return wx, wy, wz, norm, float(emission[i, 0]), float(emission[i, 1]), float(emission[i, 2]), pdf, False
    if kind == _POINT:
        positions, intensities, pmf = p_positions, p_intensities, p_pmf
        i = _search(p_cdf, u_sel)
        dx, dy, dz = positions[i, 0] - px, positions[i, 1] - py, positions[i, 2] - pz
        dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        inv_d2 = 1.0 / (dist * dist)
        return (dx / dist, dy / dist, dz / dist, dist, intensities[i, 0] * inv_d2, intensities[i, 1] * inv_d2,
                intensities[i, 2] * inv_d2, float(pmf[i]) * pk, True)
    if e_constant:
        z = 1.0 - 2.0 * u1
        r = math.sqrt(max(1.0 - z * z, 0.0))
        phi = 2 * math.pi * u2
        wx, wy, wz = r * math.cos(phi), z, r * math.sin(phi)
    else:
        h, w = e_image.shape[0], e_image.shape[1]
        pix = _search(e_cdf, u_sel)
        u = ((pix % w) + u1) / w
        v = ((pix // w) + u2) / h
        phi = 2 * math.pi * (u - 0.5)
        theta = math.pi * v
        s = math.sin(theta)
        ex, ey, ez = s * math.sin(phi), math.cos(theta), -s * math.cos(phi)
        wx, wy, wz = e_cos * ex + e_sin * ez, ey, -e_sin * ex + e_cos * ez
    lr, lg, lb = environment_radiance(e_color, e_image, e_constant, e_cos, e_sin, wx, wy, wz)
    return wx, wy, wz, np.inf, lr, lg, lb, environment_pdf(e_image, e_pmf, e_constant, e_cos, e_sin, wx, wy, wz) * pk, False


# --- the fused bounce ------------------------------------------------------------------------------


@numba.njit(nogil=True, cache=True, error_model="numpy")
def shade_and_sample(
    origins, directions, sample, throughput, prev_pdf,  # the live paths [n]
    hit, t, normal, geometric_normal, uv, surface_albedo, material_id, instance_id, primitive_id,  # their hits [n]
    u,  # [n_samples, 8] uniforms, read at each path's sample: light [0:3], BSDF lobe/direction/roulette [4:8]
    materials, instance_offsets, kinds, area, points, env,  # scene tables
    first, scatter, sample_lights, has_emitters, has_area, russian_roulette, rr_max_survival,
    radiance, aov_albedo, aov_normal, aov_depth, aov_hit,  # per-sample accumulators of the wavefront
    shadow_origin, shadow_direction, shadow_t_max, shadow_sample, shadow_contribution,  # out: compacted shadow rays
    next_origin, next_direction, next_sample, next_throughput, next_pdf,  # out: compacted surviving paths
):
    """One bounce after the closest-hit query (see the module docstring); returns the number of
    shadow rays and of surviving paths written to the front of the output arrays."""
    # Arrays out of their tables once, here: taken out of a tuple inside the row loop they cost
    # ~60 ns a row (measured), even in branches not taken.
    mat_kind, mat_albedo, mat_roughness, mat_ior, mat_emission, tex_offset, tex_size, tex_data = materials
    a_tris, a_normals, a_emission, a_cdf, a_pmf, a_density, a_base, a_holds, a_lookup = area
    p_positions, p_intensities, p_cdf, p_pmf = points
    e_color, e_image, e_cdf, e_pmf, e_constant, e_cos, e_sin, has_env = env
    pk = 1.0 / max(kinds.shape[0], 1)
    n_shadow = 0
    n_next = 0
    for i in range(origins.shape[0]):
        s = sample[i]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        tr, tg, tb = throughput[i, 0], throughput[i, 1], throughput[i, 2]
        if not hit[i]:
            if has_env:
                lr, lg, lb = environment_radiance(e_color, e_image, e_constant, e_cos, e_sin, dx, dy, dz)
                w = 1.0 if first else _power_heuristic(prev_pdf[i], environment_pdf(e_image, e_pmf, e_constant, e_cos, e_sin, dx, dy, dz) * pk)
                radiance[s, 0] += tr * lr * w
                radiance[s, 1] += tg * lg * w
                radiance[s, 2] += tb * lb * w
            continue
        # Shading geometry: normals turned to the side the ray came from.
        th = t[i]
        px, py, pz = origins[i, 0] + th * dx, origins[i, 1] + th * dy, origins[i, 2] + th * dz
        wox, woy, woz = -dx, -dy, -dz
        gx, gy, gz = geometric_normal[i, 0], geometric_normal[i, 1], geometric_normal[i, 2]
        front = _dot(gx, gy, gz, wox, woy, woz) > 0
        if not front:
            gx, gy, gz = -gx, -gy, -gz
        nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
        if _dot(nx, ny, nz, gx, gy, gz) < 0:
            nx, ny, nz = -nx, -ny, -nz
        if _dot(nx, ny, nz, wox, woy, woz) <= 0:
            nx, ny, nz = gx, gy, gz
        mid_raw = material_id[i]
        mid = max(mid_raw, 0)
        ar, ag, ab = _albedo_at(mat_albedo, tex_offset, tex_size, tex_data, mid, uv[i, 0], uv[i, 1], surface_albedo[i, 0], surface_albedo[i, 1], surface_albedo[i, 2])
        offset = max(instance_offsets[max(instance_id[i], 0)], POSITION_OFFSET * max(abs(px), abs(py), abs(pz)))
        # Emission seen at the hit (front faces only), MIS against light sampling after a bounce.
        if has_emitters and front and mid_raw >= 0:
            er, eg, eb = mat_emission[mid, 0], mat_emission[mid, 1], mat_emission[mid, 2]
            if max(er, eg, eb) > 0:
                w = 1.0
                if not first:
                    light_pdf = 0.0
                    if has_area:
                        light = _area_light_index(a_base, a_holds, a_lookup, instance_id[i], primitive_id[i])
                        if light >= 0:
                            light_pdf = _area_pdf(a_normals, a_density, light, th, dx, dy, dz) * pk
                    w = _power_heuristic(prev_pdf[i], light_pdf)
                radiance[s, 0] += tr * er * w
                radiance[s, 1] += tg * eg * w
                radiance[s, 2] += tb * eb * w
        if first:
            aov_albedo[s, 0], aov_albedo[s, 1], aov_albedo[s, 2] = ar, ag, ab
            aov_normal[s, 0], aov_normal[s, 1], aov_normal[s, 2] = nx, ny, nz
            aov_depth[s] = th
            aov_hit[s] = True
        if not scatter:
            continue
        kind, alpha, ior = mat_kind[mid], mat_roughness[mid], mat_ior[mid]
        ox, oy, oz = px + gx * offset, py + gy * offset, pz + gz * offset  # secondary rays leave from here
        # Next-event estimation: one light sample; its shadow ray is queried by the caller.
        if sample_lights:
            wx, wy, wz, dist, lr, lg, lb, lpdf, is_delta = sample_light(kinds, a_tris, a_normals, a_emission, a_cdf, a_density,
                                                                       p_positions, p_intensities, p_cdf, p_pmf, e_color, e_image,
                                                                       e_cdf, e_pmf, e_constant, e_cos, e_sin, px, py, pz,
                                                                       u[s, 0], u[s, 1], u[s, 2])
            fr, fg, fb, bpdf = _eval_pdf(kind, alpha, ior, ar, ag, ab, nx, ny, nz, wox, woy, woz, wx, wy, wz)
            if lpdf > 0 and _dot(wx, wy, wz, gx, gy, gz) > 0 and max(fr, fg, fb) > 0 and max(lr, lg, lb) > 0:
                k = n_shadow
                n_shadow += 1
                shadow_origin[k, 0], shadow_origin[k, 1], shadow_origin[k, 2] = ox, oy, oz
                if math.isfinite(dist):  # aim at the light point itself, stopping just short of it
                    shadow_direction[k, 0] = px + wx * dist - ox
                    shadow_direction[k, 1] = py + wy * dist - oy
                    shadow_direction[k, 2] = pz + wz * dist - oz
                    shadow_t_max[k] = SHADOW_T_MAX
                else:
                    shadow_direction[k, 0], shadow_direction[k, 1], shadow_direction[k, 2] = wx, wy, wz
                    shadow_t_max[k] = np.inf
                w = 1.0 if is_delta else _power_heuristic(lpdf, bpdf)
                c = w / lpdf
                shadow_sample[k] = s
                shadow_contribution[k, 0] = tr * fr * lr * c
                shadow_contribution[k, 1] = tg * fg * lg * c
                shadow_contribution[k, 2] = tb * fb * lb * c
        # BSDF sampling and Russian roulette.
        wx, wy, wz, fr, fg, fb, spdf = sample_bsdf(kind, alpha, ior, ar, ag, ab, nx, ny, nz, wox, woy, woz,
                                                   u[s, 4], u[s, 5], u[s, 6])
        nr, ng_, nb = tr * fr, tg * fg, tb * fb
        q = max(nr, ng_, nb)
        if not (spdf > 0 and _dot(wx, wy, wz, gx, gy, gz) > 0 and q > 0):
            continue
        if russian_roulette:
            q = min(q, rr_max_survival)
            if not (u[s, 7] < q):
                continue
            nr, ng_, nb = nr / q, ng_ / q, nb / q
        k = n_next
        n_next += 1
        next_origin[k, 0], next_origin[k, 1], next_origin[k, 2] = ox, oy, oz
        next_direction[k, 0], next_direction[k, 1], next_direction[k, 2] = wx, wy, wz
        next_sample[k] = s
        next_throughput[k, 0], next_throughput[k, 1], next_throughput[k, 2] = nr, ng_, nb
        next_pdf[k] = spdf
    return n_shadow, n_next


@numba.njit(nogil=True, cache=True, error_model="numpy")
def add_unoccluded(radiance, shadow_sample, shadow_contribution, blocked):
    """Add the contribution of every shadow ray that reached its light to its sample's radiance."""
    for k in range(shadow_sample.shape[0]):
        if not blocked[k]:
            s = shadow_sample[k]
            for c in range(3):
                radiance[s, c] += shadow_contribution[k, c]


@numba.njit(nogil=True, cache=True, error_model="numpy")
def camera_rays(pixel, jitter, width, height, tan_half, aspect, camera_to_world, origins, directions):
    """`Camera.generate_rays`: rays through pixels ``pixel`` [N] (row-major) at offsets ``jitter``
    [N, 2], written to ``origins`` / ``directions`` [N, 3] (unit)."""
    # float32 throughout, as torch computes it: camera rays then match to the last bit or nearly,
    # so thin geometry is hit or missed alike by both implementations.
    m = camera_to_world
    one, two = np.float32(1.0), np.float32(2.0)
    w, h = np.float32(width), np.float32(height)
    t, a = np.float32(tan_half), np.float32(aspect)
    for i in range(pixel.shape[0]):
        px = np.float32(pixel[i] % width) + jitter[i, 0]
        py = np.float32(pixel[i] // width) + jitter[i, 1]
        cx, cy, cz = _normalize32((two * px / w - one) * t * a, (one - two * py / h) * t, -one)
        dx, dy, dz = _normalize32(m[0, 0] * cx + m[0, 1] * cy + m[0, 2] * cz, m[1, 0] * cx + m[1, 1] * cy + m[1, 2] * cz,
                                  m[2, 0] * cx + m[2, 1] * cy + m[2, 2] * cz)
        origins[i, 0], origins[i, 1], origins[i, 2] = m[0, 3], m[1, 3], m[2, 3]
        directions[i, 0], directions[i, 1], directions[i, 2] = dx, dy, dz


@numba.njit(nogil=True, cache=True, error_model="numpy")
def film_add(pixel, radiance, albedo, normal, depth, hit, sum_radiance, sum_albedo, sum_normal, sum_depth, sum_hits, count):
    """`Film.add` (float64 sums; a NaN/Inf radiance sample counts as 0); returns how many were."""
    nonfinite = 0
    for i in range(pixel.shape[0]):
        p = pixel[i]
        finite = math.isfinite(radiance[i, 0]) and math.isfinite(radiance[i, 1]) and math.isfinite(radiance[i, 2])
        if not finite:
            nonfinite += 1
        for c in range(3):
            if finite:
                sum_radiance[p, c] += radiance[i, c]
            sum_albedo[p, c] += albedo[i, c]
            sum_normal[p, c] += normal[i, c]
        if hit[i]:
            sum_depth[p] += depth[i]
            sum_hits[p] += 1.0
        count[p] += 1.0
    return nonfinite


# --- whole-batch entry points of the per-row functions (tests compare them with the torch path) ---------


@numba.njit(nogil=True, cache=True, error_model="numpy")
def bsdf_sample_rows(kind, alpha, ior, albedo, normal, wo, u_lobe, u_dir, wi, weight, pdf):
    """`sample_bsdf` for every row: per-row material parameters (``kind`` [N] ...), writes ``wi``
    [N, 3], ``weight`` [N, 3] and ``pdf`` [N]."""
    for i in range(kind.shape[0]):
        r = sample_bsdf(kind[i], alpha[i], ior[i], albedo[i, 0], albedo[i, 1], albedo[i, 2], normal[i, 0], normal[i, 1],
                        normal[i, 2], wo[i, 0], wo[i, 1], wo[i, 2], u_lobe[i], u_dir[i, 0], u_dir[i, 1])
        wi[i, 0], wi[i, 1], wi[i, 2], weight[i, 0], weight[i, 1], weight[i, 2], pdf[i] = r


@numba.njit(nogil=True, cache=True, error_model="numpy")
def bsdf_eval_rows(kind, alpha, ior, albedo, normal, wo, wi, value, pdf):
    """``f cos`` [N, 3] and ``pdf`` [N] for every row (`MaterialTable.eval_pdf`)."""
    for i in range(kind.shape[0]):
        r = _eval_pdf(kind[i], alpha[i], ior[i], albedo[i, 0], albedo[i, 1], albedo[i, 2], normal[i, 0], normal[i, 1],
                      normal[i, 2], wo[i, 0], wo[i, 1], wo[i, 2], wi[i, 0], wi[i, 1], wi[i, 2])
        value[i, 0], value[i, 1], value[i, 2], pdf[i] = r


@numba.njit(nogil=True, cache=True, error_model="numpy")
def light_sample_rows(kinds, area, points, env, p, u, wi, distance, radiance, pdf, is_delta):
    """`sample_light` for every shading point ``p`` [N, 3] with uniforms ``u`` [N, 3] (`LightSet.sample`)."""
    a_tris, a_normals, a_emission, a_cdf, a_pmf, a_density, a_base, a_holds, a_lookup = area
    p_positions, p_intensities, p_cdf, p_pmf = points
    e_color, e_image, e_cdf, e_pmf, e_constant, e_cos, e_sin, has_env = env
    for i in range(p.shape[0]):
        r = sample_light(kinds, a_tris, a_normals, a_emission, a_cdf, a_density, p_positions, p_intensities, p_cdf, p_pmf,
                         e_color, e_image, e_cdf, e_pmf, e_constant, e_cos, e_sin, p[i, 0], p[i, 1], p[i, 2], u[i, 0], u[i, 1], u[i, 2])
        wi[i, 0], wi[i, 1], wi[i, 2], distance[i], radiance[i, 0], radiance[i, 1], radiance[i, 2], pdf[i], is_delta[i] = r


@numba.njit(nogil=True, cache=True, error_model="numpy")
def environment_rows(env, d, radiance, pdf):
    """`Environment.radiance` [N, 3] and `Environment.pdf` [N] for unit directions ``d`` [N, 3]."""
    color, image, cdf, pmf, is_constant, c, s, has_env = env
    for i in range(d.shape[0]):
        radiance[i, 0], radiance[i, 1], radiance[i, 2] = environment_radiance(color, image, is_constant, c, s, d[i, 0], d[i, 1], d[i, 2])
        pdf[i] = environment_pdf(image, pmf, is_constant, c, s, d[i, 0], d[i, 1], d[i, 2])
