"""Regenerate the hostile-file regression corpus: ``python tests/corpus/make_corpus.py``.

Each file sits in a folder named after the reader in ``tests/test_fuzz_readers.py::READERS`` that must refuse it
with ``ProxycodecError`` (files whose name starts with ``ok_`` must be accepted). Files marked ``bug_`` once made a
reader raise something else (or allocate without bound); they are kept as regressions.
"""

from __future__ import annotations

import json
import shutil
import struct
import sys
import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import test_fuzz_readers as F
from conftest import forged_tensor_pickle, os_system_pickle, replace_zip_record
from proxycodec.formats import container


def _hostile_gaussians() -> dict[str, bytes]:
    """Degenerate 3DGS PLYs (issue 16): no Gaussians, all in one point, NaN / Inf fields, scales of e^+-20, zero
    quaternions, an SH degree the fields do not match."""
    import tempfile

    import numpy as np
    from proxycodec.formats.inria_ply import GaussianPly, write_inria_ply

    rng = np.random.default_rng(7)
    n = 12

    def ply(**kw) -> bytes:
        a = dict(means=rng.normal(size=(n, 3)), sh=rng.normal(size=(n, 4, 3)), opacities=rng.normal(size=n),
                 scales=rng.normal(size=(n, 3)) - 3, quats=rng.normal(size=(n, 4)))
        a.update(kw)
        k = len(a["means"])
        g = GaussianPly(**{key: v[:k] for key, v in a.items()})
        with tempfile.TemporaryDirectory() as d:
            write_inria_ply(Path(d) / "g.ply", g)
            return (Path(d) / "g.ply").read_bytes()

    out = {
        "ok_seed.ply": ply(),
        "no_gaussians.ply": ply(means=np.zeros((0, 3))),
        "one_point.ply": ply(means=np.ones((n, 3)) * 0.25),
        "ok_scales_e+20.ply": ply(scales=np.full((n, 3), 20.0)),
        "ok_scales_e-20.ply": ply(scales=np.full((n, 3), -20.0)),
        "ok_zero_quaternions.ply": ply(quats=np.zeros((n, 4))),
        "ok_opacity_inf.ply": None,
        "nan_mean.ply": None,
        "inf_sh.ply": None,
        "sh_degree_mismatch.ply": None,
    }
    base = out["ok_seed.ply"]
    h = base.index(b"end_header\n") + 11
    assert (len(base) - h) % n == 0  # whole rows: the pokes below land in the first one

    def poke(offset_in_row: int, value: float) -> bytes:
        b = bytearray(base)
        b[h + offset_in_row:h + offset_in_row + 4] = struct.pack("<f", value)
        return bytes(b)

    # row layout: x y z nx ny nz f_dc(3) f_rest(9) opacity scale(3) rot(4)
    out["ok_opacity_inf.ply"] = poke(4 * 18, float("inf"))
    out["nan_mean.ply"] = poke(0, float("nan"))
    out["inf_sh.ply"] = poke(4 * 7, float("inf"))
    out["sh_degree_mismatch.ply"] = base.replace(b"property float f_rest_8\n", b"")  # 8 f_rest, rows of 9
    return out


def scene_corpus() -> dict[str, bytes]:
    """Entropy-coded scene containers (scene formats 4 and 5) with hostile sections or metadata behind valid CRCs:
    the golden file with its ANS stream flipped, an escape too many, integer nets that could overflow; format 5's
    with per-cell levels out of range (the other malformed level tables: ``test_entropy.HOSTILE_LEVELS``)."""
    import tempfile

    from test_entropy import GOLDEN, HOSTILE, HOSTILE_LEVELS, _rewrite

    out = {}
    with tempfile.TemporaryDirectory() as d:
        for case in ("stream_word_flipped", "escapes_extra", "nets_overflow"):
            meta_fn, arrays_fn = HOSTILE[case]
            out[f"{case}.pxc"] = _rewrite(GOLDEN / "scene_v4.pxc", Path(d) / "x.pxc", meta_fn, arrays_fn).read_bytes()
        for case in ("levels_out_of_range",):
            meta_fn, arrays_fn = HOSTILE_LEVELS[case]
            out[f"{case}.pxc"] = _rewrite(GOLDEN / "scene_v5.pxc", Path(d) / "x.pxc", meta_fn, arrays_fn).read_bytes()
    return out


def main() -> None:
    S = F.make_seeds()
    files: dict[str, dict[str, bytes]] = {k: {} for k in F.READERS}

    def add(reader, name, data):
        files[reader][name] = data

    # ---- PLY (generic, scaffold, inria)
    le = S["ply_le"]
    head_end = le.index(b"end_header\n") + 11
    add("ply_le", "ok_seed.ply", le)
    add("ply_le", "truncated_payload.ply", le[:-5])
    add("ply_le", "truncated_header.ply", le[: head_end - 4])
    add("ply_le", "count_1e12.ply", le.replace(b"element vertex 3", b"element vertex 1000000000000"))
    add("ply_le", "count_2pow64.ply", le.replace(b"element vertex 3", b"element vertex 18446744073709551616"))
    add("ply_le", "count_negative.ply", le.replace(b"element vertex 3", b"element vertex -3"))
    add("ply_le", "unknown_type.ply", le.replace(b"property float x", b"property float128 x"))
    add("ply_le", "non_ascii_header.ply", le.replace(b"made by", b"made \xff\xfe by"))
    add("ply_le", "no_end_header.ply", b"ply\nformat binary_little_endian 1.0\n" + b"comment x\n" * 7000)
    add("ply_le", "list_property.ply", le.replace(b"property float x", b"property list uchar int x"))
    add("ply_le", "format_2.ply", le.replace(b" 1.0\n", b" 2.0\n", 1))
    add("ply_le", "bitflip_magic.ply", b"plz" + le[3:])
    add("ply_ascii", "nan_token.ply", S["ply_ascii"].replace(b"128", b"nan"))
    add("ply_ascii", "int_out_of_range.ply", S["ply_ascii"].replace(b"255", b"256"))
    add("ply_ascii", "count_1e12.ply", S["ply_ascii"].replace(b"element vertex 3", b"element vertex 1000000000000"))
    add("ply_be", "truncated.ply", S["ply_be"][:-1])

    sc = S["scaffold_ply"]
    add("scaffold_ply", "ok_seed.ply", sc)
    add("scaffold_ply", "bug_huge_property_index.ply", sc.replace(b"f_offset_5\n", b"f_offset_99999999999\n"))
    add("scaffold_ply", "truncated.ply", sc[: len(sc) // 2])
    add("scaffold_ply", "count_1e12.ply", sc.replace(b"element vertex 3", b"element vertex 1000000000000"))
    h = sc.index(b"end_header\n") + 11
    nan_pos = bytearray(sc)
    nan_pos[h:h + 4] = struct.pack("<f", float("nan"))  # x of the first anchor
    add("scaffold_ply", "nan_position.ply", bytes(nan_pos))
    inf_feat = bytearray(sc)
    row = (len(sc) - h) // 3
    inf_feat[h + row - 4 * 12:h + row - 4 * 11] = struct.pack("<f", float("inf"))  # a scaling of anchor 0
    add("scaffold_ply", "inf_scaling.ply", bytes(inf_feat))
    add("scaffold_ply", "inria_file.ply", S["inria_ply"])
    add("scaffold_ply", "double_overflow.ply", _double_overflow(sc))

    gi = S["inria_ply"]
    add("inria_ply", "ok_seed.ply", gi)
    add("inria_ply", "bug_huge_property_index.ply", gi.replace(b"f_rest_3\n", b"f_rest_123456789012\n"))
    add("inria_ply", "truncated.ply", gi[:-7])
    add("inria_ply", "wrong_rest_count.ply", gi.replace(b"property float f_rest_8\n", b""))
    add("inria_ply", "scaffold_file.ply", sc)

    # ---- 3DGS PLYs that `proxycodec convert` must refuse with one line or turn into a finite anchor scene
    for name, data in _hostile_gaussians().items():
        add("inria_convert", name, data)

    # ---- COLMAP binary
    cb, ib, pb = S["cameras_bin"], S["images_bin"], S["points3d_bin"]
    add("cameras_bin", "ok_seed.bin", cb)
    add("cameras_bin", "count_1e9.bin", struct.pack("<Q", 10**9) + cb[8:])
    add("cameras_bin", "count_2pow64m1.bin", struct.pack("<Q", 2**64 - 1) + cb[8:])
    add("cameras_bin", "unknown_model.bin", cb[:12] + struct.pack("<i", 99) + cb[16:])
    add("cameras_bin", "huge_size.bin", cb[:16] + struct.pack("<Q", 2**63) + cb[24:])
    add("cameras_bin", "truncated.bin", cb[:-3])
    add("cameras_bin", "empty.bin", b"")
    add("images_bin", "ok_seed.bin", ib)
    add("images_bin", "count_1e9.bin", struct.pack("<Q", 10**9) + ib[8:])
    add("images_bin", "keypoints_1e12.bin", ib.replace(struct.pack("<Q", 2) + struct.pack("<dd", 1.0, 2.0),
                                                       struct.pack("<Q", 10**12) + struct.pack("<dd", 1.0, 2.0), 1))
    add("images_bin", "unterminated_name.bin", ib.replace(b"a.png\0", b"a.png" + b"x" * 300, 1)[:400])
    add("images_bin", "bug_newline_in_name_bad_pose.bin",
        ib[:8] + struct.pack("<i4d3di", 10, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 1) + b"a\nb.png\0" + struct.pack("<Q", 0))
    add("images_bin", "huge_quaternion.bin",
        ib[:8] + struct.pack("<i4d3di", 10, 1e308, 1e308, 0.0, 0.0, 0, 0, 0, 1) + b"a.png\0" + struct.pack("<Q", 0))
    add("points3d_bin", "ok_seed.bin", pb)
    add("points3d_bin", "count_1e9.bin", struct.pack("<Q", 10**9) + pb[8:])
    add("points3d_bin", "track_1e9.bin", struct.pack("<Q", 1) + struct.pack("<Q3d3BdQ", 1, 0, 0, 0, 1, 2, 3, 0.5, 10**9))
    add("points3d_bin", "track_2pow64m1.bin",
        struct.pack("<Q", 1) + struct.pack("<Q3d3BdQ", 1, 0, 0, 0, 1, 2, 3, 0.5, 2**64 - 1))
    add("points3d_bin", "nan_xyz.bin", struct.pack("<Q", 1) + struct.pack("<Q3d3BdQ", 1, float("nan"), 0, 0, 1, 2, 3, 0.5, 0))
    add("points3d_bin", "trailing.bin", pb + b"\0")

    # ---- COLMAP text
    add("cameras_txt", "ok_seed.txt", S["cameras_txt"])
    add("cameras_txt", "huge_width.txt", b"1 PINHOLE 99999999999999999999999 12 1 1 1 1\n")
    add("cameras_txt", "nan_param.txt", b"1 PINHOLE 16 12 nan 1 1 1\n")
    add("cameras_txt", "not_utf8.txt", b"1 PINHOLE \xff\xfe 12 1 1 1 1\n")
    add("cameras_txt", "few_params.txt", b"1 OPENCV 16 12 1 1 1 1\n")
    add("images_txt", "ok_seed.txt", S["images_txt"])
    add("images_txt", "no_keypoint_line.txt", b"10 1 0 0 0 0 0 0 1 a.png")
    add("images_txt", "bad_pose.txt", b"10 0 0 0 0 0 0 0 1 a.png\n\n")
    add("images_txt", "bug_nan_point3d_id.txt", b"10 1 0 0 0 0 0 0 1 a.png\n1.0 2.0 nan\n")
    add("images_txt", "keypoints_not_triples.txt", b"10 1 0 0 0 0 0 0 1 a.png\n1.0 2.0\n")
    add("points3d_txt", "ok_seed.txt", S["points3d_txt"])
    add("points3d_txt", "bug_int_beyond_int64.txt", b"101 1 2 3 0 0 99999999999999999999999 0.0\n")
    add("points3d_txt", "bug_id_beyond_int64.txt", b"99999999999999999999999 1 2 3 0 0 0 0.0\n")
    add("points3d_txt", "odd_track.txt", b"101 1 2 3 0 0 0 0.0 5\n")
    add("points3d_txt", "colour_300.txt", b"101 1 2 3 300 0 0 0.0\n")

    # ---- Blender transforms
    add("blender_json", "ok_seed.json", S["blender_json"])
    add("blender_json", "bug_deep_nesting.json", b"[" * 5000 + b"]" * 5000)
    add("blender_json", "bug_nul_in_file_path.json",
        b'{"camera_angle_x": 0.5, "frames": [{"file_path": "r_0\\u0000x", "transform_matrix": []}]}')
    add("blender_json", "int_5000_digits.json", b'{"camera_angle_x": 1' + b"0" * 5000 + b', "frames": []}')
    add("blender_json", "angle_nan.json", b'{"camera_angle_x": NaN, "frames": []}')
    add("blender_json", "singular_matrix.json", b'{"camera_angle_x": 0.5, "frames": [{"file_path": "r_0", '
                                                b'"transform_matrix": [[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,0]]}]}')
    add("blender_json", "not_utf8.json", b'{"camera_angle_x": 0.5, "frames": "\xff"}')
    add("blender_json", "list_toplevel.json", b"[]")
    far = json.loads(S["blender_json"])
    far["frames"][0]["transform_matrix"][2][3] = 1e308  # bounds overflow: the error message was multi-line
    add("blender_json", "bug_camera_at_1e308_multiline_message.json", json.dumps(far).encode())

    # ---- containers
    c = S["container"]
    add("container", "ok_seed.pxc", c)
    add("container", "wrong_magic.pxc", b"\x89PXD" + c[4:])
    add("container", "truncated_header.pxc", c[:20])
    add("container", "truncated_payload.pxc", c[:-10])
    add("container", "trailing_bytes.pxc", c + b"\0")
    flipped = bytearray(c)
    flipped[-3] ^= 0x10
    add("container", "bitflip_payload.pxc", bytes(flipped))
    add("container", "version_2.pxc", _reheader(c, version=2))
    add("container", "sections_5000.pxc", _reheader(c, n=5000))
    m, stored = F._meta_entry(b'{"k":1}', 0)
    e = {"name": "big", "codec": 1, "dtype": 1, "shape": (1 << 30,), "offset": 0, "stored": 900, "raw": 1 << 30,
         "crc": 0}
    m["offset"] = 32 + F._toc_size([m, e])
    e["offset"] = m["offset"] + len(stored)
    add("container", "section_1GiB_declared.pxc", F.forge_container([m, e], stored + b"\x28\xb5\x2f\xfd" + bytes(896)))
    e2 = dict(e, shape=(2**32, 2**32), raw=0, stored=0, codec=0)
    add("container", "shape_overflow.pxc", F.forge_container([m, e2], stored))
    m2, stored2 = F._meta_entry(b"[1, 2]", 0)
    m2["offset"] = 32 + F._toc_size([m2])
    add("container", "meta_not_object.pxc", F.forge_container([m2], stored2))
    m3, stored3 = F._meta_entry(b'{"a": NaN}', 0)
    m3["offset"] = 32 + F._toc_size([m3])
    add("container", "meta_nan.pxc", F.forge_container([m3], stored3))
    add("container_header", "wrong_magic.pxc", b"\x89PXD" + c[4:])
    add("container_header", "toc_crc.pxc", c[:40] + bytes([c[40] ^ 1]) + c[41:])

    # ---- PyTorch archives (Scaffold-GS's MLP files)
    ts, ck = S["torchscript"], S["torch_checkpoint"]
    add("torchscript", "ok_seed.pt", ts)
    add("torch_checkpoint", "ok_seed.pth", ck)
    ts = _zip(_records(ts, lambda n: "/code/" not in n))  # the forged ones without code/ (never read): smaller
    add("torchscript", "ok_without_code.pt", ts)
    for reader, seed, ext in (("torchscript", ts, "pt"), ("torch_checkpoint", ck, "pth")):
        add(reader, f"truncated.{ext}", seed[: len(seed) // 2])
        add(reader, f"evil_os_system.{ext}", replace_zip_record(seed, "/data.pkl", os_system_pickle("true")))
        add(reader, f"evil_builtins_eval.{ext}", replace_zip_record(
            seed, "/data.pkl", b"\x80\x02cbuiltins\neval\nX\x04\x00\x00\x001+1\x85R."))
        # storage 0 is the first Linear's weight, 4 x 5 floats
        add(reader, f"view_1e12_of_storage.{ext}", replace_zip_record(
            seed, "/data.pkl", forged_tensor_pickle((10**6, 10**6), (0, 0), 20)))
        add(reader, f"shape_past_storage.{ext}", replace_zip_record(
            seed, "/data.pkl", forged_tensor_pickle((5, 5), (5, 1), 20)))
        add(reader, f"storage_1e12.{ext}", replace_zip_record(seed, "/data.pkl",
                                                              forged_tensor_pickle((2, 2), (2, 1), 10**12)))
        add(reader, f"pickle_not_a_pickle.{ext}", replace_zip_record(seed, "/data.pkl", b"\x80\x02K"))
        # LONG_BINPUT 2^32 - 1: CPython's unpickler sized its memo table by it (MemoryError, or 32 GB)
        add(reader, f"bug_memo_index_2pow32.{ext}", replace_zip_record(seed, "/data.pkl",
                                                                       b"\x80\x02Nr\xff\xff\xff\xff."))
    # a __torch__ module class where only tensors may be (a torch.save file)
    add("torch_checkpoint", "script_module.pth", replace_zip_record(ck, "/data.pkl", _data_pkl(ts)))
    add("torchscript", "not_zip.pt", b"PK\x03\x04" + bytes(60))
    add("torchscript", "no_data_pkl.pt", _zip({"m/code/__torch__.py": b"import os\nos.system('true')\n"}))
    add("torchscript", "two_data_pkl.pt", _zip({"a/data.pkl": b"\x80\x02N.", "b/data.pkl": b"\x80\x02N."}))
    add("torchscript", "deflate_bomb.pt", _zip({"m/data.pkl": forged_tensor_pickle((4,), (1,), 1 << 20),
                                                "m/data/0": bytes(4 << 20)}, deflate=True))
    add("torchscript", "module_state_not_dict.pt", _zip({"m/data.pkl": b"\x80\x02c__torch__\nM\n)\x81K\x01b."}))
    add("torchscript", "tensor_not_module.pt", replace_zip_record(ts, "/data.pkl",
                                                                   forged_tensor_pickle((4,), (1,), 20)))

    # ---- Scaffold-GS cfg_args and cameras.json
    cfg = S["cfg_args"]
    add("cfg_args", "ok_seed", cfg)
    add("cfg_args", "ok_non_literal_value_is_skipped", cfg.replace(b"ratio=1", b"ratio=__import__('os').system('true')"))
    add("cfg_args", "call_not_namespace", b"__import__('os').system('true')")
    add("cfg_args", "double_star", b"Namespace(**{'a': 1})")
    add("cfg_args", "deep_nesting", b"Namespace(a=" + b"[" * 5000 + b"]" * 5000 + b")")
    add("cfg_args", "not_utf8", b"Namespace(a='\xff')")
    add("cfg_args", "truncated", cfg[: len(cfg) // 2])
    cams = S["scaffold_cameras"]
    add("scaffold_cameras", "ok_seed.json", cams)
    add("scaffold_cameras", "not_a_rotation.json", cams.replace(b"[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]",
                                                                b"[2.0, 0.0, 0.0], [0.0, 0.0, -1.0]", 1))
    add("scaffold_cameras", "nan_position.json", cams.replace(b"[0.0, -4.0, 0.5]", b"[NaN, -4.0, 0.5]", 1))
    add("scaffold_cameras", "width_float.json", cams.replace(b'"width": 16', b'"width": 16.5', 1))
    add("scaffold_cameras", "width_1e30.json", cams.replace(b'"width": 16', b'"width": 1' + b"0" * 30, 1))
    add("scaffold_cameras", "deep_nesting.json", b"[" * 5000 + b"]" * 5000)
    add("scaffold_cameras", "empty_list.json", b"[]")
    for name, data in scene_corpus().items():
        add("scene", name, data)

    for reader, items in files.items():
        d = HERE / reader
        if d.exists():
            shutil.rmtree(d)
        if not items:
            continue
        d.mkdir()
        for name, data in items.items():
            (d / name).write_bytes(data)
    total = sum(p.stat().st_size for p in HERE.glob("*/*"))
    print(f"{sum(len(v) for v in files.values())} files, {total} bytes")


def _zip(records: dict[str, bytes], deflate: bool = False) -> bytes:
    import io
    import zipfile

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED) as z:
        for name, data in records.items():
            z.writestr(name, data)
    return out.getvalue()


def _records(archive: bytes, keep=lambda name: True) -> dict[str, bytes]:
    import io
    import zipfile

    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        return {n: z.read(n) for n in z.namelist() if keep(n)}


def _data_pkl(archive: bytes) -> bytes:
    return next(v for k, v in _records(archive).items() if k.endswith("/data.pkl"))


def _reheader(c: bytes, *, version: int | None = None, n: int | None = None) -> bytes:
    magic, v, flags, nn, toc_len, toc_crc, _ = container.HEADER.unpack(c[:32])
    head = container.HEADER.pack(magic, v if version is None else version, flags, nn if n is None else n, toc_len,
                                 toc_crc, 0)
    return head[:-4] + struct.pack("<I", zlib.crc32(head[:-4])) + c[32:]


def _double_overflow(sc: bytes) -> bytes:
    """x as a double property holding 1e300 (beyond float32)."""
    h = sc.index(b"end_header\n") + 11
    head = sc[:h].replace(b"property float x\n", b"property double x\n")
    n = 3
    row = (len(sc) - h) // n
    out = bytearray(head)
    for i in range(n):
        r = sc[h + i * row:h + (i + 1) * row]
        out += struct.pack("<d", 1e300) + r[4:]
    return bytes(out)


if __name__ == "__main__":
    main()
