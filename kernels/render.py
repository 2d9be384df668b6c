"""Warp kernels of the headless ray-cast renderer: one thread per pixel, ``wp.mesh_query_ray`` per sample.

Conventions:

* Pixel ``(i, j)`` is row ``i`` from the top and column ``j`` from the left; a sample at sub-pixel
  ``(a, b)`` of an ``s x s`` grid sits at normalised device coordinates
  ``x = 2 (j + (b + 1/2) / s) / W - 1`` and ``y = 1 - 2 (i + (a + 1/2) / s) / H``.
* A perspective camera spans ``x * half_x`` and ``y * half_y`` in units of the focal length
  (``half = tan(fov / 2)``); an orthographic camera spans them in world units around the eye.
* ``mesh_query_ray`` returns barycentrics ``(u, v)`` weighting the face's corners 0, 1, 2 as
  ``(u, v, 1 - u - v)``.
* Depth is the view-space z-distance from the eye, ``+inf`` where no sample of the pixel hits.
"""

import warp as wp


@wp.func
def lut_lookup(lut: wp.array(dtype=wp.vec3), value: float):
    """Linear interpolation in a colour table spanning ``value`` in [0, 1] (clamped)."""
    n = lut.shape[0]
    x = wp.clamp(value, 0.0, 1.0) * float(n - 1)
    i0 = wp.min(int(wp.floor(x)), n - 2)
    f = x - float(i0)
    return lut[i0] * (1.0 - f) + lut[i0 + 1] * f


@wp.func
def surface_albedo(
    faces: wp.array(dtype=int),
    face: int,
    u: float,
    v: float,
    vertex_colors: wp.array(dtype=wp.vec3),
    vertex_values: wp.array(dtype=float),
    lut: wp.array(dtype=wp.vec3),
    nan_color: wp.vec3,
):
    """Albedo at a hit: per-vertex colours interpolated, or a per-vertex scalar interpolated then looked up.

    In the scalar path a negative value marks a missing (NaN) vertex; faces touching one get ``nan_color``.
    """
    i0 = faces[face * 3 + 0]
    i1 = faces[face * 3 + 1]
    i2 = faces[face * 3 + 2]
    w = 1.0 - u - v
    if lut.shape[0] > 0:
        s0 = vertex_values[i0]
        s1 = vertex_values[i1]
        s2 = vertex_values[i2]
        if s0 < 0.0 or s1 < 0.0 or s2 < 0.0:
            return nan_color
        return lut_lookup(lut, u * s0 + v * s1 + w * s2)
    return u * vertex_colors[i0] + v * vertex_colors[i1] + w * vertex_colors[i2]


@wp.func
def shade(
    albedo: wp.vec3,
    normal: wp.vec3,
    view: wp.vec3,
    light: wp.vec3,
    ambient: float,
    diffuse: float,
    specular: float,
    shininess: float,
):
    """Lambert plus ambient plus Blinn-Phong specular; all directions unit and pointing away from the surface."""
    ndl = wp.max(wp.dot(normal, light), 0.0)
    spec = 0.0
    if ndl > 0.0:
        h = wp.normalize(light + view)
        spec = specular * wp.pow(wp.max(wp.dot(normal, h), 0.0), shininess)
    return albedo * (ambient + diffuse * ndl) + wp.vec3(spec, spec, spec)


@wp.kernel(enable_backward=False)
def render_pixels(
    mesh: wp.uint64,
    faces: wp.array(dtype=int),
    vertex_normals: wp.array(dtype=wp.vec3),
    vertex_colors: wp.array(dtype=wp.vec3),
    vertex_values: wp.array(dtype=float),
    lut: wp.array(dtype=wp.vec3),
    nan_color: wp.vec3,
    eye: wp.vec3,
    forward: wp.vec3,
    right: wp.vec3,
    up: wp.vec3,
    half_x: float,
    half_y: float,
    orthographic: int,
    samples: int,
    max_t: float,
    light: wp.vec3,
    background: wp.vec3,
    ambient: float,
    diffuse: float,
    specular: float,
    shininess: float,
    flat: int,
    color: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=float),
):
    """Shaded colour (mean over ``samples x samples`` rays) and nearest depth of each pixel.

    ``vertex_normals`` is empty when ``flat`` is 1; the geometric normal of the hit face is used then.
    Back faces are shaded as front faces (open meshes show their inside).
    """
    i, j = wp.tid()
    height = color.shape[0]
    width = color.shape[1]
    inv_s = 1.0 / float(samples)
    acc = wp.vec3(0.0, 0.0, 0.0)
    nearest = float(wp.inf)
    for a in range(samples):
        for b in range(samples):
            x = 2.0 * (float(j) + (float(b) + 0.5) * inv_s) / float(width) - 1.0
            y = 1.0 - 2.0 * (float(i) + (float(a) + 0.5) * inv_s) / float(height)
            origin = eye
            direction = forward
            if orthographic != 0:
                origin = eye + (x * half_x) * right + (y * half_y) * up
            else:
                direction = wp.normalize(forward + (x * half_x) * right + (y * half_y) * up)
            q = wp.mesh_query_ray(mesh, origin, direction, max_t)
            if q.result:
                nearest = wp.min(nearest, q.t * wp.dot(direction, forward))
                geo = wp.normalize(q.normal)
                facing = 1.0
                if wp.dot(geo, direction) > 0.0:
                    facing = -1.0
                n = geo * facing
                if flat == 0:
                    f3 = q.face * 3
                    w = 1.0 - q.u - q.v
                    ns = (
                        q.u * vertex_normals[faces[f3 + 0]]
                        + q.v * vertex_normals[faces[f3 + 1]]
                        + w * vertex_normals[faces[f3 + 2]]
                    )
                    if wp.length(ns) > 1.0e-12:
                        n = wp.normalize(ns) * facing
                albedo = surface_albedo(faces, q.face, q.u, q.v, vertex_colors, vertex_values, lut, nan_color)
                acc += shade(albedo, n, -direction, light, ambient, diffuse, specular, shininess)
            else:
                acc += background
    color[i, j] = acc * (inv_s * inv_s)
    depth[i, j] = nearest
