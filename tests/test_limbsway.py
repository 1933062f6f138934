"""Limbs: a tree asset groups each first-order branch with all that grows on it, and a windy
forest sways each limb about its base, measured on the composed stage against the cantilever,
drag and gust formulas written here."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from stands import beech_and_pine, build_text

from usdforest.errors import RecipeError
from usdforest.grow.species import get_species
from usdforest.usd.limbsway import MIN_SWAY
from usdforest.usd.validate import validate
from usdforest.usd.wind import crown_of

STAND = beech_and_pine(4)
SPEED, GUSTINESS, DURATION, FPS = 10.0, 0.3, 60.0, 24.0
# the leaves do not flutter: a flight's rays meet them at rest on their limbs
WIND = (
    f"[wind]\nspeed = {SPEED}\ngustiness = {GUSTINESS}\nduration = {DURATION}\nfps = {FPS}\n"
    "flutter_angle = 0\n"
)
# the defaults of [wind]
E, RHO_WOOD, RHO_AIR, DRAG, ZETA, ATTENUATION, GUST_LENGTH = (
    8.0e9,
    900.0,
    1.204,
    0.35,
    0.1,
    2.5,
    20.0,
)
PROTOS = ("/Forest/Trees/Prototypes/Beech_0", "/Forest/Trees/Prototypes/Pine_0")


@pytest.fixture(scope="module")
def stands(tmp_path_factory):
    root = tmp_path_factory.mktemp("limbs")
    return {
        "still": build_text(root, "still", STAND),
        "windy": build_text(root, "windy", STAND + WIND),
        "stiff": build_text(root, "stiff", STAND + WIND + "branch_sway = false\n"),
    }


def _leaf_count(prim: Usd.Prim) -> int:
    n = 0
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.PointInstancer) and p.GetName() in ("Leaves", "LeafClusters"):
            n += len(UsdGeom.PointInstancer(p).GetProtoIndicesAttr().Get() or ())
    return n


def _limbs(stage: Usd.Stage, proto: str) -> list[Usd.Prim]:
    return [
        p
        for p in stage.GetPrimAtPath(f"{proto}/Branches").GetChildren()
        if p.GetName().startswith("Limb_")
    ]


@pytest.mark.parametrize("grouped", [True, False])
def test_a_limb_holds_the_wood_that_grows_from_it_and_its_leaves(tmp_path, grouped):
    """Every wood prim in a limb's group traces its ``usdforest:parent`` back to the limb's
    first prim, a first-order one off the trunk; none outside a limb does; the wood and
    leaves compose where the grown tree put them, grouped or not (a tree written without
    ``limbs`` has no group)."""
    from usdforest.usd.tree import build_tree, write_tree

    beech = get_species("european-beech")
    out = tmp_path / "beech.usda"
    write_tree(beech, out, seed=2, limbs=grouped)
    p = build_tree(beech, seed=2).placement
    stage = Usd.Stage.Open(str(out))
    cache = UsdGeom.XformCache()
    wood, holder = {}, {}
    for prim in Usd.PrimRange(stage.GetPrimAtPath("/Tree")):
        order = prim.GetAttribute("usdforest:order")
        if order.HasAuthoredValue():
            i = p.trunk if prim.GetName() == "Trunk" else int(prim.GetName()[2:])
            wood[i] = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=float)
            up = prim.GetParent().GetName()
            holder[i] = int(up[5:]) if up.startswith("Limb_") else -1
    assert sorted(wood) == list(range(p.n_wood))
    m = p.wood_matrices()
    np.testing.assert_allclose(np.array([wood[i] for i in range(p.n_wood)]), m, atol=1e-5)
    for i, limb in holder.items():
        j = i
        while p.order[j] > 1:
            j = int(p.parent[j])
        first = j
        while p.order[first] == 1 and p.parent[first] >= 0 and p.order[p.parent[first]] == 1:
            first = int(p.parent[first])
        if p.order[i] == 0 or not grouped:
            assert limb == -1
        else:
            assert limb == first and p.order[p.parent[first]] == 0
    limbs = {holder[i] for i in holder} - {-1}
    assert len(limbs) == (len(set(p.axis[p.order == 1])) if grouped else 0)
    # every leaf, wherever its instancer now is, where the placement put it
    positions = []
    for prim in Usd.PrimRange(stage.GetPrimAtPath("/Tree")):
        if prim.IsA(UsdGeom.PointInstancer) and prim.GetName() == "Leaves":
            to_tree = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=float)
            rows = np.asarray(
                UsdGeom.PointInstancer(prim).ComputeInstanceTransformsAtTime(0, 0), dtype=float
            ).reshape(-1, 4, 4)
            positions.append((rows @ to_tree)[:, 3, :3])
    got = np.concatenate(positions)
    assert len(got) == p.n_leaves > 1000
    assert (len(positions) > 20) == grouped  # the tree's own instancer, and each limb's
    order = np.lexsort(got.T)
    want = p.leaf_position.astype(np.float32).astype(float)
    np.testing.assert_allclose(got[order], want[np.lexsort(want.T)], atol=1e-5)
    assert validate(out) == []


def _tip_moves(stage: Usd.Stage, limb: Usd.Prim) -> tuple[np.ndarray, np.ndarray]:
    """The limb's base and tip moves ``(time codes, 3)`` from rest, in its tree's space."""
    xf = UsdGeom.Xformable(limb)
    base = np.append(np.array(limb.GetAttribute("usdforest:base").Get(), float), 1.0)
    tip = np.append(np.array(limb.GetAttribute("usdforest:tip").Get(), float), 1.0)
    times = range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()))
    m = np.array([np.asarray(xf.GetLocalTransformation(t), dtype=float) for t in times])
    return (base @ m - base)[:, :3], (tip @ m - tip)[:, :3]


def _von_karman(f: np.ndarray, speed: float) -> np.ndarray:
    scale = GUST_LENGTH / speed
    return 4 * scale / (1 + 70.8 * (f * scale) ** 2) ** (5 / 6)


def test_each_limb_sways_about_its_base_as_its_cantilever_in_the_gusts(stands):
    """Each limb turns about its base (which stays put), its tip moving across its axis with
    the spectrum of its own damped cantilever driven by von Kármán gusts, and as much as
    the linearised drag of its share of the crown predicts:

    f0 = (1.8751² / 2 pi) (d / 4 L²) sqrt(E / rho) (Euler-Bernoulli, clamped-free);
    static tip deflection F L³ / (8 E I), F = 1/2 rho_air Cd A U(z)², I = pi d⁴ / 64, A the
    crown's silhouette times the limb's share of the leaves, U(z) = U exp(a (z / h - 1));
    rms per direction across the limb = sqrt((2² + 0.8²) / 2) g times that, times
    sqrt(sum |H|² S / sum S). A limb the model sways less than 5 mm rms stays rigid."""
    stage = Usd.Stage.Open(str(stands["windy"]))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    scales = np.asarray(pi.GetScalesAttr().Get(), dtype=float)[:, 2]
    heights = [
        bbox.ComputeUntransformedBound(stage.GetPrimAtPath(t)).ComputeAlignedRange().GetMax()[2]
        for t in pi.GetPrototypesRel().GetTargets()
    ]
    idx = np.asarray(pi.GetProtoIndicesAttr().Get())
    tallest = max(heights[k] * s for k, s in zip(idx, scales, strict=True))
    n = int(DURATION * FPS)
    f = np.fft.rfftfreq(n, 1 / FPS)
    checked, rigid, ratios = 0, 0, []
    for proto in PROTOS:
        prim = stage.GetPrimAtPath(proto)
        area = crown_of(prim).area
        total = _leaf_count(prim)
        limbs = _limbs(stage, proto)
        assert len(limbs) > 20
        for limb in limbs:
            base_move, tip_move = _tip_moves(stage, limb)
            assert np.abs(base_move).max() < 1e-5
            base = np.array(limb.GetAttribute("usdforest:base").Get(), float)
            tip = np.array(limb.GetAttribute("usdforest:tip").Get(), float)
            axis = (tip - base) / np.linalg.norm(tip - base)
            # a turn: the tip keeps its distance from the base
            reach = np.linalg.norm(tip + tip_move - base, axis=1)
            np.testing.assert_allclose(reach, np.linalg.norm(tip - base), atol=1e-4)
            across = tip_move - np.outer(tip_move @ axis, axis)
            d = 2 * limb.GetAttribute("usdforest:radius").Get()
            length = limb.GetAttribute("usdforest:length").Get()
            f0 = 1.8751**2 / (2 * math.pi) * d / (4 * length**2) * math.sqrt(E / RHO_WOOD)
            h2 = 1 / ((1 - (f / f0) ** 2) ** 2 + (2 * ZETA * f / f0) ** 2)
            s = _von_karman(f, SPEED)
            s[0] = s[-1] = 0.0  # no mean; the Nyquist bin has no phase of its own
            z = 0.5 * (base[2] + tip[2])
            u = SPEED * math.exp(ATTENUATION * (min(z / tallest, 1.0) - 1.0))
            share = _leaf_count(limb) / total
            force = 0.5 * RHO_AIR * DRAG * area * share * u**2
            static = force * length**3 / (8 * E * math.pi * d**4 / 64)
            sigma = math.sqrt((4 + 0.64) / 2) * GUSTINESS * static
            want = 2 * sigma**2 * (h2 * s).sum() / s.sum()
            if not UsdGeom.Xformable(limb).GetOrderedXformOps():
                # a limb swaying under 5 mm rms stays rigid
                assert math.sqrt(want) < MIN_SWAY * 1.01 and not np.any(tip_move)
                rigid += 1
                continue
            assert math.sqrt(want) > MIN_SWAY * 0.99
            if f0 > FPS / 4:  # a sway the frames cannot follow: only its quasi-static part
                continue
            power = (np.abs(np.fft.rfft(across, axis=0)) ** 2).sum(axis=1)
            # the tip's spectrum is the cantilever's response to the gusts
            assert abs(f[np.argmax(power)] - f[np.argmax(h2 * s)]) <= 1.5 / DURATION
            ratios.append(float((across**2).sum(axis=1).mean() / want))
            checked += 1
    assert checked > 40 and rigid > 0
    # every limb's variance is the model's (only the half-float angles stand between them)
    np.testing.assert_allclose(ratios, 1.0, rtol=0.01)


def test_limbs_rest_without_the_wind_and_with_branch_sway_off(stands):
    """At the default time and with the wind layer muted, every limb stands where the asset
    put it; a still forest, and one whose wind keeps ``branch_sway = false``, groups no limb
    (nothing would move it)."""
    windy = Usd.Stage.Open(str(stands["windy"]))
    for limb in _limbs(windy, PROTOS[0]):
        m = np.asarray(UsdGeom.Xformable(limb).GetLocalTransformation(), dtype=float)
        np.testing.assert_allclose(m, np.eye(4), atol=1e-7)
    layer = Sdf.Layer.FindOrOpen(str(stands["windy"].parent / "windy_assets" / "wind.usdc"))
    sampled = [
        x for x in _walk(layer) if "xformOp:rotateXYZ:sway" in layer.GetPrimAtPath(x).attributes
    ]
    swaying = [
        limb
        for p in PROTOS
        for limb in _limbs(windy, p)
        if UsdGeom.Xformable(limb).GetOrderedXformOps()
    ]
    assert sorted(sampled) == sorted(limb.GetPath() for limb in swaying)
    muted = Usd.Stage.Open(str(stands["windy"]))
    muted.MuteLayer(layer.identifier)
    stiff = Usd.Stage.Open(str(stands["stiff"]))
    still = Usd.Stage.Open(str(stands["still"]))
    limbs = _limbs(muted, PROTOS[0])
    assert len(limbs) > 20
    for limb in limbs:
        assert not UsdGeom.Xformable(limb).GetOrderedXformOps()
    for stage in (stiff, still):
        for proto in PROTOS:
            assert _limbs(stage, proto) == []
    stiff_layer = Sdf.Layer.FindOrOpen(str(stands["stiff"].parent / "stiff_assets" / "wind.usdc"))
    assert not any(
        "xformOp:rotateXYZ:sway" in stiff_layer.GetPrimAtPath(x).attributes
        for x in _walk(stiff_layer)
    )
    assert validate(stands["windy"]) == []


def _walk(layer: Sdf.Layer) -> list[Sdf.Path]:
    out = []
    layer.Traverse(Sdf.Path.absoluteRootPath, lambda p: out.append(p) if p.IsPrimPath() else None)
    return out


def test_the_sensors_see_each_limb_where_it_sways(stands):
    """The sensors' scene holds each swaying limb as an instance of its own on its tree: the
    still scene moved to t (SceneMotion) holds every leaf and wood piece where the scene read
    at t holds them, rays cast at it meet what rays cast at the scene read at t meet, and the
    limbs' own turns move the leaves by centimetres beyond their trees' sway (the same gusts
    with ``branch_sway = false``)."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion
    from usdforest.sensors.sonar.wood import scene_cylinders

    t = 1.52  # between the time codes 36 and 37
    moved, at_rest = {}, {}
    for name in ("windy", "stiff"):
        still = extract_scene(stands[name], cache=False)
        motion = SceneMotion(stands[name], still)
        # the two forests hold their leaves in different instancers: match them at rest
        rest = np.round(still.leaves.centre, 5)
        order = np.lexsort(rest.T)
        moved[name] = motion.leaves(t, still.leaves).centre[order]
        at_rest[name] = still.leaves.centre[order]
        if name == "stiff":
            assert still.sources.part is None
            continue
        stage = Usd.Stage.Open(str(stands[name]))
        swaying = [
            limb
            for p in PROTOS
            for limb in _limbs(stage, p)
            if UsdGeom.Xformable(limb).GetOrderedXformOps()
        ]
        assert int((still.sources.part >= 0).sum()) == len(swaying) > 40
        now = extract_scene(stands[name], time=t, cache=False)
        moved_leaves = motion.leaves(t, still.leaves)
        np.testing.assert_allclose(moved_leaves.centre, now.leaves.centre, atol=1e-5)
        np.testing.assert_allclose(moved_leaves.normal, now.leaves.normal, atol=1e-5)
        wood = motion.cylinders(t, scene_cylinders(still, 0.5))
        want = scene_cylinders(now, 0.5)
        np.testing.assert_allclose(wood.centre, want.centre, atol=1e-4)
        # a fan of rays from 12 m up over the stand, down through both crowns
        rng = np.random.default_rng(0)
        d = np.column_stack([rng.uniform(-0.6, 0.6, (4000, 2)), -np.ones(4000)])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.tile([10.0, 10.0, 24.0], (4000, 1))
        hit = SceneCaster(still).moved(motion.at(t)).first_hit(o, d)
        ref = SceneCaster(now).first_hit(o, d)
        assert hit.hit.sum() > 1000
        np.testing.assert_array_equal(hit.hit, ref.hit)
        np.testing.assert_allclose(hit.t[hit.hit], ref.t[ref.hit], atol=1e-4)
        np.testing.assert_array_equal(hit.cls, ref.cls)
    np.testing.assert_allclose(at_rest["windy"], at_rest["stiff"], atol=1e-4)
    gap = np.linalg.norm(moved["windy"] - moved["stiff"], axis=1)
    assert np.percentile(gap, 99) > 0.01


def test_branch_sway_must_be_a_boolean(tmp_path):
    with pytest.raises(RecipeError, match=r"wind\.branch_sway: expected true or false"):
        build_text(tmp_path, "bad", STAND + WIND + 'branch_sway = "yes"\n')
    assert not (tmp_path / "bad.usda").exists()


def test_the_swaying_limbs_found_are_kept_with_the_stages_prototypes(stands, tmp_path, monkeypatch):
    """Finding a prototype's swaying limbs walks its prims (0.8 s in the windy default
    forest): a second extraction reads them from the scene cache, and places the same parts
    as an extraction without it."""
    from usdforest.sensors.scene import walk as scene_module
    from usdforest.sensors.scene.extraction import extract_scene

    monkeypatch.setenv("USDFOREST_CACHE", str(tmp_path / "cache"))
    real = scene_module.moving_parts
    walked = []

    def counted(proto):
        walked.append(proto)
        return real(proto)

    monkeypatch.setattr(scene_module, "moving_parts", counted)
    first = extract_scene(stands["windy"])
    assert len(walked) == 2  # the beech's and the pine's prototypes
    again = extract_scene(stands["windy"])
    assert len(walked) == 2  # read back
    bare = extract_scene(stands["windy"], cache=False)
    assert len(walked) == 4
    assert len(bare.sources.parts) > 10
    for scene in (first, again):
        assert scene.sources.parts == bare.sources.parts
        np.testing.assert_array_equal(scene.sources.part, bare.sources.part)
        np.testing.assert_array_equal(scene.instances.matrix, bare.instances.matrix)
