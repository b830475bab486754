"""Procedural indoor scenes as plain Python dicts, and camera paths through them.

The paper renders 10 indoor scenes from Bitterli's repository; those assets cannot be fetched here, so
each of the 10 TRAINING families below generates rooms of one character (living room, kitchen, ...) with
random size, furniture, colours, materials and lights from a seed. The GENERALIZATION families use object
kinds that never occur in training (tori, knots, disks, lathe "statues"), standing in for the paper's
generalization set of unseen objects.

A scene is a dict in Mitsuba's ``load_dict`` format with three plain-data extensions that
``bench.render.to_mitsuba_dict`` converts (so this module never imports Mitsuba):
``to_world``/``to_uv`` as 4x4 nested lists, ``{'type': 'srd_mesh', 'vertices', 'faces'}`` for generated
meshes, and ``srd_*`` metadata keys (dropped before loading). Object shapes are keyed
``obj_<kind>_<index>``; that key names the object kind. Coordinates: metres, z up, the room spans
[0, W] x [0, D] x [0, H].
"""
import zlib

import numpy as np

TRAIN_FAMILIES = ("living_room", "kitchen", "bathroom", "bedroom", "office",
                  "gallery", "dining", "studio", "library", "atrium")
GENERALIZATION_FAMILIES = ("torus_hall", "knot_room", "statue_room", "disk_room")
FAMILIES = TRAIN_FAMILIES + GENERALIZATION_FAMILIES

DIFFUSE_BSDFS = {"diffuse"}
GLOSSY_BSDFS = {"roughconductor", "roughplastic", "principled", "roughdielectric"}
DELTA_BSDFS = {"conductor", "dielectric", "thindielectric", "plastic"}
TRANSMISSIVE_BSDFS = {"dielectric", "roughdielectric", "thindielectric"}
METALS = ("Au", "Cu", "Al", "Ag", "Cr")
# Camera volume: away from walls and above the furniture (every free-standing object is under 1.25 m).
CAMERA_WALL_MARGIN = 0.7
CAMERA_MIN_HEIGHT = 1.35


# ----------------------------------------------------------------------------------------------------------
# Transforms (4x4 nested lists, column vectors, as Mitsuba's to_world)


def translate(v):
    m = np.eye(4)
    m[:3, 3] = v
    return m


def scaling(v):
    return np.diag([*np.broadcast_to(np.asarray(v, float), (3,)), 1.0])


def rotate_z(degrees):
    a = np.radians(degrees)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return m


def frame(center, normal, half_u, half_v):
    """Matrix mapping Mitsuba's [-1,1]^2 rectangle/disk (normal +z) to a patch facing ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)  # (u, v, n) right-handed, so the emitting side is +n
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u * half_u, v * half_v, n, center
    return m


def patch(center, u, v):
    """Matrix mapping Mitsuba's [-1,1]^2 rectangle to centre + s*u + t*v; its normal is u x v (normalised)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    n = np.cross(u, v)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, n / np.linalg.norm(n), center
    return m


def _list(m):
    return np.asarray(m, float).tolist()


# ----------------------------------------------------------------------------------------------------------
# Materials


def rgb(c):
    return {"type": "rgb", "value": [float(x) for x in c]}


def random_color(rng, saturation=(0.2, 0.9), value=(0.25, 0.85)):
    """A colour with random hue; varied hues matter (the paper saw colour fading with few scene colours)."""
    h, s, v = rng.uniform(0, 1), rng.uniform(*saturation), rng.uniform(*value)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    return v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)


def diffuse(color):
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": rgb(color)}}


def checker(color0, color1, tiles):
    tex = {"type": "checkerboard", "color0": rgb(color0), "color1": rgb(color1),
           "to_uv": _list(scaling([tiles, tiles, 1]))}
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": tex}}


def roughplastic(color, alpha):
    return {"type": "roughplastic", "diffuse_reflectance": rgb(color), "alpha": float(alpha)}


def metal(rng, alpha):
    return {"type": "roughconductor", "material": str(rng.choice(METALS)), "alpha": float(alpha)}


def glass(ior=1.5):
    return {"type": "dielectric", "int_ior": float(ior)}


def principled(color, roughness, metallic=0.0):
    return {"type": "principled", "base_color": rgb(color), "roughness": float(roughness),
            "metallic": float(metallic)}


def random_material(rng, kinds=("diffuse", "checker", "plastic", "metal", "principled", "glass")):
    """One material of a kind drawn from ``kinds`` with random colour and roughness."""
    kind = rng.choice(kinds)
    color = random_color(rng)
    if kind == "diffuse":
        return diffuse(color)
    if kind == "checker":
        return checker(color, random_color(rng), int(rng.integers(2, 8)))
    if kind == "plastic":
        return roughplastic(color, rng.uniform(0.05, 0.5))
    if kind == "metal":
        return metal(rng, rng.uniform(0.02, 0.5))
    if kind == "principled":
        return principled(color, rng.uniform(0.1, 0.9), metallic=float(rng.uniform() < 0.3))
    return glass(rng.uniform(1.4, 1.6))


# ----------------------------------------------------------------------------------------------------------
# Generated meshes


def _grid_faces(rows, cols, wrap_cols=True):
    """Triangles of a rows x cols vertex grid (columns wrap around when ``wrap_cols``)."""
    faces = []
    for r in range(rows - 1):
        for c in range(cols if wrap_cols else cols - 1):
            a, b = r * cols + c, r * cols + (c + 1) % cols
            faces += [[a, b, a + cols], [b, b + cols, a + cols]]
    return np.array(faces, np.int32)


def lathe_mesh(profile_z, profile_r, segments=32):
    """Closed surface of revolution about z: rings of radius r at height z, capped by two pole vertices."""
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    rings = [np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(phi, z)], 1)
             for z, r in zip(profile_z, profile_r)]
    vertices = np.concatenate(rings + [[[0, 0, profile_z[0]]], [[0, 0, profile_z[-1]]]])
    faces = _grid_faces(len(profile_z), segments)
    bottom, top, last = len(vertices) - 2, len(vertices) - 1, (len(profile_z) - 1) * segments
    caps = [[bottom, (c + 1) % segments, c] for c in range(segments)]
    caps += [[top, last + c, last + (c + 1) % segments] for c in range(segments)]
    return vertices.astype(np.float32), np.concatenate([faces, np.array(caps, np.int32)])


def cylinder_mesh(radius, height, segments=32):
    """Closed cylinder (base at z=0) with flat caps."""
    z = np.array([0.0, 0.0, height, height])
    r = np.array([1e-4, radius, radius, 1e-4])
    return lathe_mesh(z, r, segments)


def blob_mesh(rng, radius, rings=16, segments=32):
    """A lumpy sphere: radius modulated by a few random low-frequency spherical waves."""
    theta = np.linspace(0.05, np.pi - 0.05, rings)
    z = -radius * np.cos(theta)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    amp, freq, phase = rng.uniform(0.05, 0.2, 3), rng.integers(1, 4, 3), rng.uniform(0, 2 * np.pi, 3)
    vertices = []
    for t, zz in zip(theta, z):
        bump = 1 + sum(a * np.sin(f * phi + p) * np.sin(t) for a, f, p in zip(amp, freq, phase))
        r = radius * np.sin(t) * bump
        vertices.append(np.stack([r * np.cos(phi), r * np.sin(phi), np.full_like(phi, zz)], 1))
    vertices = np.concatenate(vertices + [[[0, 0, -radius]], [[0, 0, radius]]])
    faces = _grid_faces(rings, segments)
    bottom, top, last = len(vertices) - 2, len(vertices) - 1, (rings - 1) * segments
    caps = [[bottom, (c + 1) % segments, c] for c in range(segments)]
    caps += [[top, last + c, last + (c + 1) % segments] for c in range(segments)]
    return vertices.astype(np.float32), np.concatenate([faces, np.array(caps, np.int32)])


def tube_mesh(curve, radius, sides=12):
    """Closed tube of ``radius`` around a closed polyline ``curve`` (N x 3), using parallel-ish frames."""
    n = len(curve)
    tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0])
    normal = np.cross(tangent, ref)
    small = np.linalg.norm(normal, axis=1) < 1e-3
    normal[small] = np.cross(tangent[small], [1.0, 0.0, 0.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = (np.cos(ang)[None, :, None] * normal[:, None] + np.sin(ang)[None, :, None] * binormal[:, None])
    vertices = (curve[:, None] + radius * ring).reshape(-1, 3)
    faces = []
    for i in range(n):
        for s in range(sides):
            a, b = i * sides + s, i * sides + (s + 1) % sides
            c, d = ((i + 1) % n) * sides + s, ((i + 1) % n) * sides + (s + 1) % sides
            faces += [[a, c, b], [b, c, d]]
    return vertices.astype(np.float32), np.array(faces, np.int32)


def torus_mesh(major, minor, segments=48, sides=16):
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    return tube_mesh(np.stack([major * np.cos(t), major * np.sin(t), np.zeros_like(t)], 1), minor, sides)


def knot_mesh(p, q, size, tube, segments=160):
    """(p, q) torus knot of overall radius ~``size``."""
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    r = size * (0.6 + 0.3 * np.cos(q * t))
    curve = np.stack([r * np.cos(p * t), r * np.sin(p * t), size * 0.3 * np.sin(q * t)], 1)
    return tube_mesh(curve, tube)


def statue_mesh(rng, height):
    """A procedural 'statue' (bust / chess-piece silhouette): a lathe with base, waist, shoulders, head."""
    z = np.linspace(0, height, 24)
    u = z / height
    r = height * (0.18 - 0.1 * u + 0.07 * np.exp(-((u - 0.55) / 0.08) ** 2)
                  + 0.09 * np.exp(-((u - 0.85) / 0.07) ** 2) * rng.uniform(0.8, 1.3))
    r = r * (1 + 0.05 * np.sin(u * rng.uniform(10, 25)))
    r[0] = r[-1] = 1e-4
    return lathe_mesh(z, np.maximum(r, 1e-4), 40)


def mesh(vertices, faces, to_world, bsdf):
    return {"type": "srd_mesh", "vertices": vertices, "faces": faces, "to_world": _list(to_world),
            "bsdf": bsdf}


# ----------------------------------------------------------------------------------------------------------
# Rooms, lights, objects


def room_size(seed):
    """(W, D, H) of the room of ``seed``; depends on the seed only, so cameras can be made without the scene."""
    rng = np.random.default_rng([int(seed), 0])
    return float(rng.uniform(4.0, 7.0)), float(rng.uniform(4.0, 7.0)), float(rng.uniform(2.7, 3.4))


def room_shapes(rng, size, floor_bsdf, wall_bsdf, ceiling_bsdf, skylight=None):
    """Floor, ceiling and four walls; ``skylight`` = (cx, cy, half) leaves a square hole in the ceiling."""
    w, d, h = size
    e = 0.05  # walls overlap their neighbours by e so no ray slips through an exactly touching seam
    hw, hd, hh = w / 2 + e, d / 2 + e, h / 2 + e
    shapes = {
        "room_floor": {"type": "rectangle", "to_world": _list(patch([w / 2, d / 2, 0], [hw, 0, 0], [0, hd, 0])),
                       "bsdf": floor_bsdf},
        "room_wall_x0": {"type": "rectangle", "to_world": _list(patch([0, d / 2, h / 2], [0, hd, 0], [0, 0, hh])),
                         "bsdf": wall_bsdf},
        "room_wall_x1": {"type": "rectangle", "to_world": _list(patch([w, d / 2, h / 2], [0, 0, hh], [0, hd, 0])),
                         "bsdf": wall_bsdf},
        "room_wall_y0": {"type": "rectangle", "to_world": _list(patch([w / 2, 0, h / 2], [0, 0, hh], [hw, 0, 0])),
                         "bsdf": wall_bsdf},
        "room_wall_y1": {"type": "rectangle", "to_world": _list(patch([w / 2, d, h / 2], [hw, 0, 0], [0, 0, hh])),
                         "bsdf": wall_bsdf},
    }
    if skylight is None:
        shapes["room_ceiling"] = {"type": "rectangle", "bsdf": ceiling_bsdf,
                                  "to_world": _list(patch([w / 2, d / 2, h], [0, hd, 0], [hw, 0, 0]))}
        return shapes
    cx, cy, half = skylight
    x0, x1, y0, y1 = cx - half, cx + half, cy - half, cy + half
    # Four ceiling strips around the hole (overlapping by e):
    # [0,x0]x[0,d], [x1,w]x[0,d], [x0,x1]x[0,y0], [x0,x1]x[y1,d].
    strips = [(-e, x0, -e, d + e), (x1, w + e, -e, d + e), (x0 - e, x1 + e, -e, y0), (x0 - e, x1 + e, y1, d + e)]
    for i, (ax, bx, ay, by) in enumerate(strips):
        shapes[f"room_ceiling_{i}"] = {
            "type": "rectangle", "bsdf": ceiling_bsdf,
            "to_world": _list(patch([(ax + bx) / 2, (ay + by) / 2, h], [0, (by - ay) / 2, 0],
                                    [(bx - ax) / 2, 0, 0]))}
    return shapes


def area_light(center, normal, half_u, half_v, radiance):
    return {"type": "rectangle", "to_world": _list(frame(center, normal, half_u, half_v)),
            "emitter": {"type": "area", "radiance": rgb(radiance)},
            "bsdf": {"type": "diffuse", "reflectance": rgb([0.8, 0.8, 0.8])}}


def warm_white(rng, power):
    """Light colour around white (slightly warm or cool) scaled to ``power``."""
    return power * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 1.0)])


def ceiling_lights(rng, size, count, half, power):
    """``count`` downward-facing area lights of half-size ``half`` just below the ceiling."""
    w, d, h = size
    return {f"light_ceiling_{i}": area_light([rng.uniform(1, w - 1), rng.uniform(1, d - 1), h - 0.01],
                                             [0, 0, -1], half, half, warm_white(rng, power))
            for i in range(count)}


def window_light(rng, size, power):
    """A bright window-like emitter on a random wall, facing into the room (sky-blue tint)."""
    w, d, h = size
    wall = int(rng.integers(4))
    centers = [([0.01, d / 2, h * 0.55], [1, 0, 0]), ([w - 0.01, d / 2, h * 0.55], [-1, 0, 0]),
               ([w / 2, 0.01, h * 0.55], [0, 1, 0]), ([w / 2, d - 0.01, h * 0.55], [0, -1, 0])]
    center, normal = centers[wall]
    color = power * np.array([rng.uniform(0.75, 0.9), rng.uniform(0.85, 0.95), 1.0])
    return {"light_window": area_light(center, normal, rng.uniform(0.6, 1.2), rng.uniform(0.4, 0.7), color)}


def sky_lights(rng, size, skylight, sun=True):
    """Environment light (constant sky) entering through the skylight, plus an optional directional sun."""
    lights = {"light_sky": {"type": "constant", "radiance": rgb(rng.uniform(0.6, 1.2) * np.array([0.7, 0.8, 1.0]))}}
    if sun:
        cx, cy, _ = skylight
        target = np.array([cx + rng.uniform(-0.8, 0.8), cy + rng.uniform(-0.8, 0.8), 0.0])
        source = np.array([cx, cy, size[2]])
        lights["light_sun"] = {"type": "directional", "direction": (target - source).tolist(),
                               "irradiance": rgb(rng.uniform(3, 8) * np.array([1.0, 0.95, 0.85]))}
    return lights


def _floor_spot(rng, size, margin=0.8):
    w, d, _ = size
    return rng.uniform(margin, w - margin), rng.uniform(margin, d - margin)


def cube(center, half, angle, bsdf):
    m = translate(center) @ rotate_z(angle) @ scaling(half)
    return {"type": "cube", "to_world": _list(m), "bsdf": bsdf}


def sphere(center, radius, bsdf):
    return {"type": "sphere", "center": [float(c) for c in center], "radius": float(radius), "bsdf": bsdf}


def place_cubes(rng, size, count, bsdfs, height=(0.3, 0.9), half_xy=(0.2, 0.6)):
    """Furniture-like boxes standing on the floor."""
    out = []
    for _ in range(count):
        x, y = _floor_spot(rng, size)
        hz = rng.uniform(*height) / 2
        out.append(cube([x, y, hz], [rng.uniform(*half_xy), rng.uniform(*half_xy), hz],
                        rng.uniform(0, 90), bsdfs(rng)))
    return out


def place_spheres(rng, size, count, bsdfs, radius=(0.12, 0.35), lift=0.0):
    out = []
    for _ in range(count):
        x, y = _floor_spot(rng, size)
        r = rng.uniform(*radius)
        out.append(sphere([x, y, r + lift * rng.uniform()], r, bsdfs(rng)))
    return out


def place_cylinders(rng, size, count, bsdfs, radius=(0.06, 0.25), height=(0.2, 1.0)):
    out = []
    for _ in range(count):
        x, y = _floor_spot(rng, size)
        v, f = cylinder_mesh(rng.uniform(*radius), rng.uniform(*height))
        out.append(mesh(v, f, translate([x, y, 0]), bsdfs(rng)))
    return out


def place_blobs(rng, size, count, bsdfs, radius=(0.15, 0.4)):
    out = []
    for _ in range(count):
        x, y = _floor_spot(rng, size)
        r = rng.uniform(*radius)
        v, f = blob_mesh(rng, r)
        out.append(mesh(v, f, translate([x, y, r * 1.1]) @ rotate_z(rng.uniform(0, 360)), bsdfs(rng)))
    return out


def place_wall_cubes(rng, size, count, bsdfs):
    """Tall shelves/cabinets standing against walls (outside the camera volume, so they can be tall)."""
    w, d, h = size
    out = []
    for _ in range(count):
        wall = int(rng.integers(4))
        hz = rng.uniform(0.9, min(2.2, h - 0.3)) / 2
        along = rng.uniform(0.3, 0.8)
        depth = rng.uniform(0.15, 0.25)
        if wall < 2:
            x = depth if wall == 0 else w - depth
            out.append(cube([x, rng.uniform(1, d - 1), hz], [depth, along, hz], 0, bsdfs(rng)))
        else:
            y = depth if wall == 2 else d - depth
            out.append(cube([rng.uniform(1, w - 1), y, hz], [along, depth, hz], 0, bsdfs(rng)))
    return out


def _pick(kinds):
    """Material sampler restricted to ``kinds`` (used to give each family its character)."""
    return lambda rng: random_material(rng, kinds)


# ----------------------------------------------------------------------------------------------------------
# Families: one function each, (rng, room size, wall/floor/ceiling already drawn) -> what the family puts
# in the room: {"objects": {kind: [shape dicts]}, "lights": {...}} and, when it changes them, "floor" or
# "skylight" (a ceiling opening (cx, cy, half size)). The order of the rng draws is part of the dataset.

ANY_MATERIAL = _pick(("diffuse", "checker", "plastic", "metal", "principled", "glass"))


def _living_room(rng, size):
    return {"objects": {"cube": place_cubes(rng, size, 4, _pick(("diffuse", "principled", "checker"))),
                        "sphere": place_spheres(rng, size, 3, _pick(("plastic", "metal", "principled")))},
            "lights": ceiling_lights(rng, size, 1, rng.uniform(0.5, 0.9), 6.0)}


def _kitchen(rng, size):
    return {"objects": {"cube": place_cubes(rng, size, 3, _pick(("plastic", "principled")), height=(0.85, 0.95)),
                        "cylinder": place_cylinders(rng, size, 5, _pick(("metal",)), height=(0.15, 0.5))},
            "lights": {**window_light(rng, size, 12.0), **ceiling_lights(rng, size, 1, 0.2, 60.0)}}


def _bathroom(rng, size):
    floor = checker([0.9, 0.9, 0.9], random_color(rng), int(rng.integers(6, 14)))
    return {"floor": floor,
            "objects": {"sphere": place_spheres(rng, size, 3, _pick(("glass",)), lift=0.6),
                        "cylinder": place_cylinders(rng, size, 3, _pick(("glass", "metal"))),
                        "cube": place_cubes(rng, size, 2, _pick(("plastic",)))},
            "lights": ceiling_lights(rng, size, 1, 0.12, 250.0)}


def _bedroom(rng, size):
    return {"objects": {"cube": place_cubes(rng, size, 3, _pick(("diffuse", "principled")), height=(0.4, 0.7),
                                            half_xy=(0.3, 0.9)),
                        "blob": place_blobs(rng, size, 2, _pick(("diffuse", "principled")))},
            "lights": ceiling_lights(rng, size, 1, rng.uniform(0.8, 1.2), 3.5)}


def _office(rng, size):
    return {"objects": {"cube": place_cubes(rng, size, 4, _pick(("plastic", "metal")), height=(0.7, 0.8)),
                        "cylinder": place_cylinders(rng, size, 4, _pick(("plastic", "principled")))},
            "lights": ceiling_lights(rng, size, 3, 0.15, 50.0)}


def _gallery(rng, size):
    pedestals = place_cubes(rng, size, 4, _pick(("diffuse",)), height=(0.7, 0.85), half_xy=(0.2, 0.25))
    balls = []
    for ped in pedestals:  # a metal sphere of random roughness on top of each pedestal
        m = np.array(ped["to_world"])
        r = rng.uniform(0.12, 0.2)
        balls.append(sphere([m[0, 3], m[1, 3], 2 * m[2, 3] + r], r, metal(rng, rng.uniform(0.01, 0.6))))
    return {"objects": {"cube": pedestals, "sphere": balls}, "lights": ceiling_lights(rng, size, 2, 0.1, 150.0)}


def _dining(rng, size):
    skylight = (size[0] / 2, size[1] / 2, rng.uniform(0.5, 0.9))
    return {"skylight": skylight,
            "objects": {"cube": place_cubes(rng, size, 2, _pick(("principled", "diffuse")), height=(0.7, 0.8),
                                            half_xy=(0.4, 0.8)),
                        "cylinder": place_cylinders(rng, size, 4, _pick(("glass",)), height=(0.15, 0.3)),
                        "sphere": place_spheres(rng, size, 4, _pick(("diffuse", "plastic")), radius=(0.05, 0.12))},
            "lights": {**window_light(rng, size, 8.0), **sky_lights(rng, size, skylight, sun=False)}}


def _studio(rng, size):
    objects = {"blob": place_blobs(rng, size, 4, _pick(("plastic", "principled", "metal")))}
    # One large soft light and one small hard one.
    return {"objects": objects,
            "lights": {"light_soft": ceiling_lights(rng, size, 1, 0.8, 4.0)["light_ceiling_0"],
                       "light_hard": ceiling_lights(rng, size, 1, 0.1, 150.0)["light_ceiling_0"]}}


def _library(rng, size):
    skylight = (size[0] / 2, size[1] / 2, rng.uniform(0.4, 0.7))
    return {"skylight": skylight,
            "objects": {"cube": place_wall_cubes(rng, size, 5, _pick(("principled", "diffuse")))
                        + place_cubes(rng, size, 2, _pick(("principled", "plastic")))},
            "lights": sky_lights(rng, size, skylight, sun=True)}


def _atrium(rng, size):
    skylight = (size[0] / 2, size[1] / 2, min(size[0], size[1]) / 2 - 0.6)
    return {"skylight": skylight,
            "objects": {"cylinder": place_cylinders(rng, size, 4, _pick(("diffuse", "principled")),
                                                    radius=(0.1, 0.2), height=(0.6, 1.2)),
                        "sphere": place_spheres(rng, size, 2, ANY_MATERIAL),
                        "blob": place_blobs(rng, size, 1, _pick(("glass", "metal")))},
            "lights": sky_lights(rng, size, skylight, sun=True)}


def _torus_hall(rng, size):
    tori = []
    for _ in range(4):
        x, y = _floor_spot(rng, size)
        major = rng.uniform(0.2, 0.4)
        minor = major * rng.uniform(0.2, 0.4)
        v, f = torus_mesh(major, minor)
        tilt = np.array(frame([x, y, major + minor + 0.05], rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 0.5], 1, 1))
        tori.append(mesh(v, f, tilt, ANY_MATERIAL(rng)))
    return {"objects": {"torus": tori}, "lights": ceiling_lights(rng, size, 2, 0.3, 25.0)}


def _knot_room(rng, size):
    knots = []
    for _ in range(4):
        x, y = _floor_spot(rng, size)
        s = rng.uniform(0.3, 0.45)
        v, f = knot_mesh(int(rng.choice([2, 3])), int(rng.choice([3, 5])), s, s * 0.12)
        knots.append(mesh(v, f, translate([x, y, s + 0.1]) @ rotate_z(rng.uniform(0, 360)), ANY_MATERIAL(rng)))
    return {"objects": {"knot": knots},
            "lights": {**window_light(rng, size, 10.0), **ceiling_lights(rng, size, 1, 0.25, 30.0)}}


def _statue_room(rng, size):
    statues = []
    for _ in range(5):
        x, y = _floor_spot(rng, size)
        v, f = statue_mesh(rng, rng.uniform(0.7, 1.15))
        statues.append(mesh(v, f, translate([x, y, 0]), _pick(("diffuse", "metal", "principled", "glass"))(rng)))
    return {"objects": {"statue": statues}, "lights": ceiling_lights(rng, size, 2, 0.15, 80.0)}


def _disk_room(rng, size):
    disks = []
    for _ in range(8):
        x, y = _floor_spot(rng, size, margin=0.5)
        r = rng.uniform(0.25, 0.6)
        normal = rng.normal(size=3) * [1, 1, 0.5] + [0, 0, 1.0]
        m = frame([x, y, rng.uniform(0.05, 1.1)], normal, r, r)
        disks.append({"type": "disk", "to_world": _list(m), "bsdf": _pick(("diffuse", "checker", "metal"))(rng)})
    return {"objects": {"disk": disks},
            "lights": {**window_light(rng, size, 10.0), **ceiling_lights(rng, size, 1, 0.5, 8.0)}}


FAMILY_CONTENT = {
    "living_room": _living_room, "kitchen": _kitchen, "bathroom": _bathroom, "bedroom": _bedroom,
    "office": _office, "gallery": _gallery, "dining": _dining, "studio": _studio, "library": _library,
    "atrium": _atrium, "torus_hall": _torus_hall, "knot_room": _knot_room, "statue_room": _statue_room,
    "disk_room": _disk_room,
}


def _family_content(family, rng, size):
    """Objects (dict kind -> list of shape dicts), lights, room materials and skylight of one family."""
    if family not in FAMILY_CONTENT:
        raise ValueError(f"unknown scene family {family!r}; known: {FAMILIES}")
    wall = diffuse(random_color(rng, (0.0, 0.4), (0.5, 0.85)))  # every family draws these first
    floor = checker(random_color(rng), random_color(rng), int(rng.integers(3, 10)))
    content = FAMILY_CONTENT[family](rng, size)
    room = (content.get("floor", floor), wall, diffuse([0.8, 0.8, 0.8]))
    return content["objects"], content["lights"], room, content.get("skylight")


def make_scene(family, seed):
    """Deterministic scene dict of ``family`` for ``seed`` (same arguments -> identical dict)."""
    size = room_size(seed)
    rng = np.random.default_rng([int(seed), zlib.crc32(family.encode())])
    objects, lights, (floor, wall, ceiling), skylight = _family_content(family, rng, size)
    scene = {"type": "scene"}
    scene.update(room_shapes(rng, size, floor, wall, ceiling, skylight))
    for kind, shapes in objects.items():
        for i, shape in enumerate(shapes):
            scene[f"obj_{kind}_{i}"] = shape
    scene.update(lights)
    scene["srd_meta"] = {"family": family, "seed": int(seed), "room": list(size)}
    return scene


# ----------------------------------------------------------------------------------------------------------
# Cameras


def camera_path(scene_seed, view_index, T, fov_range=(50.0, 70.0), speed=0.06):
    """T camera dicts {'origin', 'target', 'up', 'fov'} moving smoothly (constant velocity) through the room.

    The start is uniform inside the camera volume (away from walls, above the furniture), the target
    uniform in the lower middle of the room (where objects stand) at least 1.8 m away; origin and
    target drift ``speed`` metres per frame in random directions, the origin staying inside the camera
    volume.
    """
    w, d, h = room_size(scene_seed)
    rng = np.random.default_rng([int(scene_seed), 1, int(view_index)])
    lo = np.array([CAMERA_WALL_MARGIN, CAMERA_WALL_MARGIN, CAMERA_MIN_HEIGHT])
    hi = np.array([w - CAMERA_WALL_MARGIN, d - CAMERA_WALL_MARGIN, h - 0.4])
    origin = rng.uniform(lo, hi)
    # Aim at the middle of the floor area, where the objects stand (they are placed 0.8 m from the walls).
    for _ in range(100):
        target = rng.uniform([0.2 * w, 0.2 * d, 0.1], [0.8 * w, 0.8 * d, 0.9])
        if np.linalg.norm(target - origin) > 1.8:
            break
    move = rng.normal(size=3) * [1, 1, 0.3]
    move *= speed / np.linalg.norm(move)
    drift = rng.normal(size=3) * [1, 1, 0.3]
    drift *= speed / np.linalg.norm(drift)
    fov = float(rng.uniform(*fov_range))
    cams = []
    for t in range(T):
        o = np.clip(origin + t * move, lo, hi)
        cams.append({"origin": o.tolist(), "target": (target + t * drift).tolist(), "up": [0.0, 0.0, 1.0],
                     "fov": fov})
    return cams


# ----------------------------------------------------------------------------------------------------------
# Features


def _bsdf_types(value, out):
    """Collect the plugin types of every BSDF in a (nested) scene dict."""
    if isinstance(value, dict):
        kind = value.get("type")
        if kind in DIFFUSE_BSDFS | GLOSSY_BSDFS | DELTA_BSDFS:
            out.append(value)
        for key, item in value.items():
            if key not in ("vertices", "faces"):
                _bsdf_types(item, out)
    return out


def object_kinds(scene):
    """Object kinds (from 'obj_<kind>_<i>' keys) present in a scene dict."""
    return sorted({key.split("_")[1] for key in scene if key.startswith("obj_")})


def scene_features(scene):
    """What the renderer and manifest need to know about a scene dict.

    Returns {'bsdf_types', 'object_kinds', 'glossy', 'transmissive', 'specular_chain', 'all_diffuse',
    'max_depth', 'left_out'}: ``left_out`` maps a gBuffer pass to why it need not be rendered (roughness is
    the constant 1 when every BSDF is diffuse), ``max_depth`` is 12 when light can pass through glass
    (caustics and see-through need long specular chains) and 6 otherwise.
    """
    bsdfs = _bsdf_types(scene, [])
    types = sorted({b["type"] for b in bsdfs})
    transmissive = any(t in TRANSMISSIVE_BSDFS for t in types) or any(
        b["type"] == "principled" and float(b.get("spec_trans", 0)) > 0 for b in bsdfs)
    specular_chain = any(t in DELTA_BSDFS for t in types)
    glossy = any(t in GLOSSY_BSDFS for t in types)
    all_diffuse = set(types) <= DIFFUSE_BSDFS
    left_out = {"roughness": "all BSDFs diffuse: roughness is the constant 1"} if all_diffuse else {}
    return {"bsdf_types": types, "object_kinds": object_kinds(scene), "glossy": glossy,
            "transmissive": transmissive, "specular_chain": specular_chain, "all_diffuse": all_diffuse,
            "max_depth": 12 if transmissive else 6, "left_out": left_out}
