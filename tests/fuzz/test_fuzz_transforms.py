"""Fuzzed transforms.json: load_scene returns a valid Scene or raises InputError, nothing else.

Inputs are valid-looking documents whose keys and values are drawn from numbers (huge, tiny,
negative, NaN, inf), strings (paths leaving the folder, NUL bytes, very long names), nested
lists and dicts; plus raw bytes and byte-level mutations of the real file.
"""
from __future__ import annotations

import json
import math

from fuzz_helpers import loads_or_refuses, scene_copy
from hypothesis import event, given
from hypothesis import strategies as st

INTERESTING_FLOATS = st.sampled_from([0.0, -0.0, -1.0, 1e-300, 1e-45, 1e39, -1e39, 1e308, math.pi, 2 * math.pi,
                                      float("nan"), float("inf"), -float("inf"), 0.6911112070083618])
NUMBERS = st.one_of(INTERESTING_FLOATS, st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(-(2**70), 2**70), st.sampled_from([10**400, -(10**400)]), st.booleans())
TEXT = st.one_of(st.text(max_size=20), st.sampled_from(
    ["", ".", "..", "/", "../outside/photo.png", "../../../../../../etc/passwd", "/etc/passwd", "train",
     "./train/r_1", "train/r_1.png", "./train/../train/r_2", "a\0b", "n" * 256, "~/r_1", "./test/r_0",
     "./train/r\n1", "train/r_1\t"]))
JUNK = st.recursive(st.one_of(st.none(), NUMBERS, TEXT),
                    lambda inner: st.one_of(st.lists(inner, max_size=5),
                                            st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                    max_leaves=12)


@st.composite
def matrices(draw):
    kind = draw(st.sampled_from(["rigid", "perturbed", "shaped", "junk"]))
    if kind == "junk":
        return draw(JUNK)
    if kind == "shaped":
        rows, cols = draw(st.integers(0, 5)), draw(st.integers(0, 5))
        return [[draw(NUMBERS) for _ in range(cols)] for _ in range(rows)]
    angle = draw(st.floats(-math.pi, math.pi))
    c, s = math.cos(angle), math.sin(angle)
    m = [[c, -s, 0.0, draw(st.floats(-10, 10))], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
    if kind == "perturbed":
        i, j = draw(st.integers(0, 3)), draw(st.integers(0, 3))
        m[i][j] = draw(NUMBERS)
    return m


FILE_PATHS = st.one_of(st.sampled_from(["./train/r_1", "./train/r_2", "./train/r_3", "./train/r_4"]), TEXT, JUNK)
INTRINSIC_KEYS = ["camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h",
                  "k1", "k2", "k3", "k4", "p1", "p2", "is_fisheye", "camera_model",
                  # nerfstudio's files: a mask per frame, a point cloud
                  "mask_path", "ply_file_path"]
INTRINSICS = st.dictionaries(st.sampled_from(INTRINSIC_KEYS),
                             st.one_of(NUMBERS, st.floats(0.1, 3.0), st.floats(1, 100), JUNK), max_size=5)


@st.composite
def documents(draw):
    frames = draw(st.lists(st.one_of(
        st.fixed_dictionaries({"file_path": FILE_PATHS, "transform_matrix": matrices()}).flatmap(
            lambda fr: INTRINSICS.map(lambda extra: {**fr, **extra})),
        JUNK), max_size=5))
    doc = {"camera_angle_x": draw(st.one_of(st.just(0.6911112070083618), NUMBERS, JUNK)), "frames": frames}
    doc.update(draw(INTRINSICS))
    if draw(st.booleans()):
        doc["frames"] = draw(JUNK)
    return doc


@given(doc=documents(), load_images=st.booleans(), test_file=st.sampled_from(["keep", "remove", "same"]))
def test_structured_transforms(demo_base, doc, load_images, test_file):
    with scene_copy(demo_base) as (scene, outside):
        (scene / "transforms_train.json").write_text(json.dumps(doc))
        if test_file == "remove":
            (scene / "transforms_test.json").unlink()
        elif test_file == "same":
            (scene / "transforms_test.json").write_text(json.dumps(doc))
        event(loads_or_refuses(scene, outside, load_images=load_images))


@given(data=st.data())
def test_transforms_bytes(demo_base, data):
    with scene_copy(demo_base) as (scene, outside):
        path = scene / "transforms_train.json"
        raw = path.read_bytes()
        kind = data.draw(st.sampled_from(["random", "truncate", "flip", "splice"]))
        if kind == "random":
            raw = data.draw(st.binary(max_size=2000))
        elif kind == "truncate":
            raw = raw[:data.draw(st.integers(0, len(raw)))]
        elif kind == "flip":
            for _ in range(data.draw(st.integers(1, 8))):
                i = data.draw(st.integers(0, len(raw) - 1))
                raw = raw[:i] + bytes([data.draw(st.integers(0, 255))]) + raw[i + 1:]
        else:
            i = data.draw(st.integers(0, len(raw)))
            raw = raw[:i] + data.draw(st.sampled_from(
                [b"[" * 5000, b"1" * 5000, b"\xff\xfe", b"NaN", b"-Infinity", b"1e999", b'"\\ud800"', b"\0"])) + raw[i:]
        path.write_bytes(raw)
        event(f"{kind}: {loads_or_refuses(scene, outside, load_images=False)}")


PLAUSIBLE = {"camera_angle_x": st.floats(0.01, 3.1), "camera_angle_y": st.floats(0.01, 3.1),
             "fl_x": st.floats(0.5, 200.0), "fl_y": st.floats(0.5, 200.0), "cx": st.floats(-20.0, 40.0),
             "cy": st.floats(-20.0, 40.0), "w": st.integers(0, 20), "h": st.integers(0, 20),
             "k1": st.floats(-2.0, 2.0), "k2": st.floats(-2.0, 2.0), "k3": st.floats(-2.0, 2.0),
             "k4": st.floats(-2.0, 2.0), "p1": st.floats(-0.5, 0.5), "p2": st.floats(-0.5, 0.5),
             "camera_model": st.sampled_from(["OPENCV", "OPENCV_FISHEYE", "PINHOLE", "EQUIRECTANGULAR"]),
             "mask_path": st.sampled_from(["./train/r_1.png", "./test/r_0.png", "transforms_test.json", "train"]),
             "ply_file_path": st.sampled_from(["transforms_test.json", "train/r_1.png", "none.ply", "."])}


@st.composite
def edits(draw, doc: dict) -> dict:
    """The real document with one to four fields changed: plausible intrinsics (distortion and
    all), a matrix entry, a path, a value of any type, a deleted key or a duplicated frame."""
    doc = json.loads(json.dumps(doc))
    for _ in range(draw(st.integers(1, 4))):
        frames = doc["frames"] if isinstance(doc.get("frames"), list) else []
        targets = [doc] + [fr for fr in frames if isinstance(fr, dict)]
        target = targets[draw(st.integers(0, len(targets) - 1))]
        op = draw(st.sampled_from(["plausible", "plausible", "matrix", "path", "any", "delete", "duplicate"]))
        if op == "plausible":
            key = draw(st.sampled_from(sorted(PLAUSIBLE)))
            target[key] = draw(PLAUSIBLE[key])
        elif op == "matrix":
            m = target.get("transform_matrix")
            if isinstance(m, list) and len(m) == 4 and all(isinstance(row, list) and len(row) == 4 for row in m):
                m[draw(st.integers(0, 3))][draw(st.integers(0, 3))] = draw(st.one_of(NUMBERS, st.floats(-2, 2)))
        elif op == "path" and target is not doc:
            target["file_path"] = draw(FILE_PATHS)
        elif op == "any":
            target[draw(st.sampled_from(INTRINSIC_KEYS + ["file_path", "transform_matrix", "frames"]))] = draw(JUNK)
        elif op == "delete" and target:
            del target[draw(st.sampled_from(sorted(target)))]
        elif op == "duplicate" and frames:
            frames.append(json.loads(json.dumps(frames[draw(st.integers(0, len(frames) - 1))])))
    return doc


@given(data=st.data(), load_images=st.booleans(), downscale=st.sampled_from([1.0, 2.0, 3.5, 1000.0]))
def test_edited_transforms(demo_base, data, load_images, downscale):
    with scene_copy(demo_base) as (scene, outside):
        path = scene / "transforms_train.json"
        path.write_text(json.dumps(data.draw(edits(json.loads(path.read_text())))))
        event(loads_or_refuses(scene, outside, load_images=load_images, downscale=downscale))
