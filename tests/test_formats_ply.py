"""PLY readers/writers: generic PLY, Scaffold-GS anchor PLY, INRIA 3DGS PLY."""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from proxycodec.formats.inria_ply import (
    SH_C0,
    GaussianPly,
    inria_attribute_names,
    read_inria_ply,
    rgb_to_sh_dc,
    sh_dc_to_rgb,
    write_inria_ply,
)
from proxycodec.formats.ply import MAX_HEADER_BYTES, encode_ply, read_ply, read_ply_header, write_ply
from proxycodec.formats.scaffold_ply import (
    ScaffoldPly,
    read_scaffold_ply,
    scaffold_attribute_names,
    write_scaffold_ply,
)

from proxycodec.errors import ProxycodecError


def _header(
    count: int, props: list[tuple[str, str]], fmt: str = "binary_little_endian", extra: str = ""
) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {count}"]
    lines += [f"property {t} {n}" for t, n in props]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode("ascii")


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


def _raises(path, match: str):
    """pytest.raises for ProxycodecError whose message names ``path`` and matches ``match``."""

    class _Ctx:
        def __enter__(self):
            self.ctx = pytest.raises(ProxycodecError, match=match)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.ctx.__exit__(*exc)
            msg = str(self.info.value)
            assert "\n" not in msg
            assert msg.startswith(str(path)), msg
            return out

    return _Ctx()


# ============================================================================================== generic PLY
class TestGenericPly:
    def test_header_bytes_match_plyfile(self, tmp_path):
        dt = np.dtype(
            [
                ("x", "<f4"),
                ("y", "<f4"),
                ("d", "<f8"),
                ("c", "u1"),
                ("i", "<i4"),
                ("s", "<i2"),
                ("us", "<u2"),
                ("ui", "<u4"),
                ("ch", "i1"),
            ]
        )
        arr = np.zeros(2, dt)
        arr["x"] = [1.5, -2]
        arr["i"] = [-7, 1 << 30]
        write_ply(tmp_path / "a.ply", arr)
        raw = (tmp_path / "a.ply").read_bytes()
        expect = (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property double d\nproperty uchar c\nproperty int i\nproperty short s\nproperty ushort us\n"
            b"property uint ui\nproperty char ch\nend_header\n"
        )
        assert raw == expect + arr.tobytes()
        assert encode_ply(arr) == raw
        header, back = read_ply(tmp_path / "a.ply")
        assert header.count == 2 and header.names == dt.names
        assert back.dtype == dt and back.tobytes() == arr.tobytes()

    def test_comments_and_crlf_and_aliases(self, tmp_path):
        arr = np.array([(1.0, 2)], dtype=[("x", "<f4"), ("k", "u1")])
        raw = (
            b"ply\r\nformat binary_little_endian 1.0\r\ncomment made by hand\r\nobj_info x\r\n"
            b"element vertex 1\r\nproperty float32 x\r\nproperty uint8 k\r\nend_header\r\n"
        ) + arr.tobytes()
        header, back = read_ply(_write(tmp_path / "a.ply", raw))
        assert header.comments == ("made by hand",)
        assert back.tobytes() == arr.tobytes()
        write_ply(tmp_path / "b.ply", arr, comments=["hello"])
        assert (
            (tmp_path / "b.ply")
            .read_bytes()
            .startswith(b"ply\nformat binary_little_endian 1.0\ncomment hello\n")
        )

    def test_big_endian_and_ascii_agree_with_little_endian(self, tmp_path):
        dt = np.dtype([("x", "<f4"), ("n", "<i4"), ("c", "u1")])
        arr = np.array([(0.25, -3, 7), (1e-3, 100000, 255)], dt)
        big = _header(2, [("float", "x"), ("int", "n"), ("uchar", "c")], "binary_big_endian")
        big += arr.astype(dt.newbyteorder(">")).tobytes()
        _, b = read_ply(_write(tmp_path / "be.ply", big))
        asc = (
            _header(2, [("float", "x"), ("int", "n"), ("uchar", "c")], "ascii")
            + b"0.25 -3 7\n0.001 100000 255\n"
        )
        _, a = read_ply(_write(tmp_path / "as.ply", asc))
        assert b.dtype == dt and b.tobytes() == arr.tobytes()
        assert a.dtype == dt and a.tobytes() == arr.tobytes()

    def test_empty_vertex_element_and_empty_face_element(self, tmp_path):
        raw = _header(0, [("float", "x")], extra="element face 0\nproperty list uchar int vertex_indices\n")
        header, data = read_ply(_write(tmp_path / "e.ply", raw))
        assert header.count == 0 and data.shape == (0,)

    @settings(max_examples=25, deadline=None)
    @given(
        st.lists(
            st.tuples(
                st.floats(width=32, allow_nan=False), st.integers(0, 255), st.integers(-(2**31), 2**31 - 1)
            ),
            max_size=20,
        )
    )
    def test_round_trip_property(self, rows):
        arr = np.array(rows, dtype=[("x", "<f4"), ("c", "u1"), ("i", "<i4")])
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            p = os.path.join(d, "r.ply")
            write_ply(p, arr)
            _, back = read_ply(p)
            assert back.tobytes() == arr.tobytes()
            assert Path(p).read_bytes() == encode_ply(arr)

    # ---------------------------------------------------------------------------------------- malformed input
    def test_missing_file_and_directory(self, tmp_path):
        with _raises(tmp_path / "nope.ply", "file not found"):
            read_ply(tmp_path / "nope.ply")
        with _raises(tmp_path, "directory"):
            read_ply(tmp_path)
        with _raises(tmp_path / "nope.ply", "file not found"):
            read_ply_header(tmp_path / "nope.ply")

    def test_not_a_ply(self, tmp_path):
        p = _write(tmp_path / "x.ply", b"\x89PNG\r\n\x1a\n" + b"\0" * 100)
        with _raises(p, "not a PLY"):
            read_ply(p)
        with _raises(_write(tmp_path / "e.ply", b""), "not a PLY"):
            read_ply(tmp_path / "e.ply")

    def test_header_without_end_header(self, tmp_path):
        p = _write(
            tmp_path / "h.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        )
        with _raises(p, "end_header"):
            read_ply(p)

    def test_header_too_long(self, tmp_path):
        p = _write(
            tmp_path / "h.ply",
            b"ply\nformat binary_little_endian 1.0\n"
            + b"comment "
            + b"a" * MAX_HEADER_BYTES
            + b"\nelement vertex 0\nproperty float x\nend_header\n",
        )
        with _raises(p, "end_header.*within|longer than"):
            read_ply(p)

    def test_truncated_payload(self, tmp_path):
        raw = _header(3, [("float", "x"), ("float", "y")]) + b"\0" * (3 * 8 - 1)
        with _raises(tmp_path / "t.ply", "truncated"):
            read_ply(_write(tmp_path / "t.ply", raw))

    def test_trailing_bytes(self, tmp_path):
        raw = _header(1, [("float", "x")]) + b"\0" * 5
        with _raises(tmp_path / "t.ply", "unexpected bytes"):
            read_ply(_write(tmp_path / "t.ply", raw))

    def test_absurd_vertex_count_fails_before_allocating(self, tmp_path):
        raw = _header(10**18, [("float", "x")] * 1 + [("double", "y")]) + b"\0" * 12
        with _raises(tmp_path / "a.ply", "truncated.*10000000000000000"):
            read_ply(_write(tmp_path / "a.ply", raw))
        asc = _header(10**18, [("float", "x")], "ascii") + b"1\n"
        with _raises(tmp_path / "b.ply", "truncated"):
            read_ply(_write(tmp_path / "b.ply", asc))
        bad = _header(1, [("float", "x")]).replace(b"vertex 1", b"vertex -1")
        with _raises(tmp_path / "c.ply", "malformed element"):
            read_ply(_write(tmp_path / "c.ply", bad))

    def test_list_property_rejected(self, tmp_path):
        raw = _header(1, [("float", "x"), ("list uchar int", "idx")]) + b"\0" * 9
        with _raises(tmp_path / "l.ply", "'idx'.*list property"):
            read_ply(_write(tmp_path / "l.ply", raw))

    def test_other_nonempty_element_rejected(self, tmp_path):
        raw = _header(1, [("float", "x")], extra="element face 2\nproperty list uchar int vertex_indices\n")
        with _raises(tmp_path / "f.ply", "face.*not supported"):
            read_ply(_write(tmp_path / "f.ply", raw + b"\0" * 4))

    @pytest.mark.parametrize(
        "mutation,match",
        [
            ((b"binary_little_endian 1.0", b"binary_little_endian 2.0"), "unsupported PLY format"),
            ((b"binary_little_endian 1.0", b"binary_middle_endian 1.0"), "unsupported PLY format"),
            ((b"property float y", b"property half y"), "unknown type 'half'"),
            ((b"property float y", b"property float x"), "repeat"),
            ((b"property float y", b"propertee float y"), "unknown keyword"),
            ((b"element vertex 1", b"element vertex 1 2"), "malformed element"),
            ((b"element vertex 1", b"element vertex one"), "malformed element"),
            ((b"property float y", b"property float"), "malformed property"),
            ((b"property float y", "property float \u00e9".encode("latin-1")), "non-ASCII"),
        ],
    )
    def test_malformed_headers(self, tmp_path, mutation, match):
        raw = _header(1, [("float", "x"), ("float", "y")]).replace(*mutation) + b"\0" * 8
        with _raises(tmp_path / "m.ply", match):
            read_ply(_write(tmp_path / "m.ply", raw))

    def test_ascii_errors(self, tmp_path):
        asc = _header(2, [("float", "x"), ("uchar", "c")], "ascii")
        with _raises(tmp_path / "a.ply", "not a number"):
            read_ply(_write(tmp_path / "a.ply", asc + b"1 2\nfoo 3\n"))
        with _raises(tmp_path / "b.ply", "holds 3 values"):
            read_ply(_write(tmp_path / "b.ply", asc + b"1.5 2\n3.25\n"))
        with _raises(tmp_path / "c.ply", "'c'.*not uint8"):
            read_ply(_write(tmp_path / "c.ply", asc + b"1 2\n3 256\n"))

    def test_writer_rejects_unsupported_data(self, tmp_path):
        with pytest.raises(ProxycodecError, match="structured"):
            write_ply(tmp_path / "x.ply", np.zeros((3, 2), np.float32))
        with pytest.raises(ProxycodecError, match="unsupported type"):
            write_ply(tmp_path / "x.ply", np.zeros(2, dtype=[("v", "<f4", (3,))]))
        with pytest.raises(ProxycodecError, match="unsupported type"):
            write_ply(tmp_path / "x.ply", np.zeros(2, dtype=[("v", "<i8")]))
        assert os.listdir(tmp_path) == []


# ============================================================================================== Scaffold-GS
def _scaffold_bytes_by_hand(pos, off, feat, opacity, scale, rot) -> bytes:
    """The exact bytes Scaffold-GS's save_ply + plyfile write, built row by row with struct (independent of
    the code under test): offsets [M, K, 3] go out transposed (all x components, then y, then z)."""
    m, k, _ = off.shape
    f = feat.shape[1]
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {m}"]
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_offset_{i}" for i in range(3 * k)]
    names += [f"f_anchor_feat_{i}" for i in range(f)] + ["opacity"] + [f"scale_{i}" for i in range(6)]
    names += [f"rot_{i}" for i in range(4)]
    lines += [f"property float {n}" for n in names] + ["end_header"]
    out = ("\n".join(lines) + "\n").encode("ascii")
    for a in range(m):
        row = list(pos[a]) + [0.0, 0.0, 0.0]
        for axis in range(3):
            row += [off[a, j, axis] for j in range(k)]
        row += list(feat[a]) + [opacity[a]] + list(scale[a]) + list(rot[a])
        out += struct.pack(f"<{len(row)}f", *row)
    return out


def _random_scaffold(m=7, k=10, f=32, seed=0) -> ScaffoldPly:
    rng = np.random.default_rng(seed)
    return ScaffoldPly(
        rng.normal(size=(m, 3)),
        rng.normal(size=(m, k, 3)),
        rng.normal(size=(m, f)),
        rng.normal(size=(m, 6)) - 3,
        rng.normal(size=(m, 3)),
        rng.normal(size=m),
        rng.normal(size=(m, 4)),
    )


class TestScaffoldPly:
    def test_hand_built_file_reads_and_rewrites_byte_exact(self, tmp_path):
        rng = np.random.default_rng(1)
        m, k, f = 3, 10, 32
        pos = rng.normal(size=(m, 3)).astype(np.float32)
        off = rng.normal(size=(m, k, 3)).astype(np.float32)
        feat = rng.normal(size=(m, f)).astype(np.float32)
        opac = rng.normal(size=m).astype(np.float32)
        scale = rng.normal(size=(m, 6)).astype(np.float32)
        rot = np.tile(np.float32([1, 0, 0, 0]), (m, 1))
        raw = _scaffold_bytes_by_hand(pos, off, feat, opac, scale, rot)
        p = _write(tmp_path / "point_cloud.ply", raw)
        s = read_scaffold_ply(p)
        assert (s.n_anchors, s.n_offsets, s.feature_dim) == (m, k, f)
        np.testing.assert_array_equal(s.positions, pos)
        np.testing.assert_array_equal(s.offsets, off)  # un-transposed: offsets[a, j] = (x_j, y_j, z_j)
        np.testing.assert_array_equal(s.features, feat)
        np.testing.assert_array_equal(s.scalings, scale)
        np.testing.assert_array_equal(s.opacity, opac)
        np.testing.assert_array_equal(s.rotations, rot)
        np.testing.assert_array_equal(s.normals, 0)
        write_scaffold_ply(tmp_path / "again.ply", s)
        assert (tmp_path / "again.ply").read_bytes() == raw

    @pytest.mark.parametrize("k,f", [(10, 32), (5, 8), (1, 1)])
    def test_round_trip_infers_k_and_f(self, tmp_path, k, f):
        s = _random_scaffold(m=9, k=k, f=f, seed=k)
        write_scaffold_ply(tmp_path / "s.ply", s)
        back = read_scaffold_ply(tmp_path / "s.ply")
        assert back == s
        assert (back.n_offsets, back.feature_dim) == (k, f)
        assert read_ply_header(tmp_path / "s.ply").names == tuple(scaffold_attribute_names(k, f))

    def test_defaults_match_scaffold_initialisation(self):
        s = ScaffoldPly(np.zeros((2, 3)), np.zeros((2, 10, 3)), np.zeros((2, 32)), np.zeros((2, 6)))
        np.testing.assert_array_equal(s.normals, 0)
        np.testing.assert_allclose(1 / (1 + np.exp(-s.opacity)), 0.1, rtol=1e-6)
        np.testing.assert_array_equal(s.rotations, [[1, 0, 0, 0]] * 2)

    def test_empty_scene_round_trips(self, tmp_path):
        s = _random_scaffold(m=0)
        write_scaffold_ply(tmp_path / "e.ply", s)
        assert read_scaffold_ply(tmp_path / "e.ply") == s

    def test_nan_in_unused_fields_is_preserved_bitwise(self, tmp_path):
        s = _random_scaffold(m=3)
        op = s.opacity.copy()
        op[1] = np.float32("nan")
        s2 = ScaffoldPly(s.positions, s.offsets, s.features, s.scalings, s.normals, op, s.rotations)
        write_scaffold_ply(tmp_path / "n.ply", s2)
        assert read_scaffold_ply(tmp_path / "n.ply") == s2

    @pytest.mark.parametrize(
        "field_name,prop",
        [
            ("positions", "y"),
            ("offsets", "f_offset_13"),
            ("features", "f_anchor_feat_4"),
            ("scalings", "scale_5"),
        ],
    )
    @pytest.mark.parametrize("bad", [np.nan, np.inf])
    def test_non_finite_values_rejected_naming_the_field(self, tmp_path, field_name, prop, bad):
        s = _random_scaffold(m=4)
        write_scaffold_ply(tmp_path / "ok.ply", s)
        header, data = read_ply(tmp_path / "ok.ply")
        data[prop][2] = bad
        write_ply(tmp_path / "bad.ply", data)
        with _raises(
            tmp_path / "bad.ply", f"'{field_name}' holds NaN or Inf \\(first at vertex 2, property {prop}\\)"
        ):
            read_scaffold_ply(tmp_path / "bad.ply")
        arrays = {f: getattr(s, f).copy() for f in ("positions", "offsets", "features", "scalings")}
        arrays[field_name].reshape(-1)[5] = bad
        with pytest.raises(ProxycodecError, match=f"ScaffoldPly.{field_name} holds NaN"):
            ScaffoldPly(**arrays)

    def test_wrong_fields(self, tmp_path):
        s = _random_scaffold(m=2, k=2, f=3)
        write_scaffold_ply(tmp_path / "ok.ply", s)
        _, data = read_ply(tmp_path / "ok.ply")
        names = list(data.dtype.names)

        def variant(name, keep=None, extra=None):
            cols = [n for n in names if keep is None or keep(n)]
            arr = np.zeros(2, dtype=[(n, "<f4") for n in cols] + ([(extra, "<f4")] if extra else []))
            for n in cols:
                arr[n] = data[n]
            write_ply(tmp_path / name, arr)
            return tmp_path / name

        with _raises(tmp_path / "a.ply", "lacks properties \\['opacity'\\]"):
            read_scaffold_ply(variant("a.ply", keep=lambda n: n != "opacity"))
        with _raises(tmp_path / "b.ply", "6 scale_"):
            read_scaffold_ply(variant("b.ply", keep=lambda n: n != "scale_5"))
        with _raises(tmp_path / "c.ply", "not a multiple of 3"):
            read_scaffold_ply(variant("c.ply", keep=lambda n: n != "f_offset_5"))
        with _raises(tmp_path / "d.ply", "f_anchor_feat_1 is missing"):
            read_scaffold_ply(variant("d.ply", keep=lambda n: n != "f_anchor_feat_1"))
        with _raises(tmp_path / "e.ply", "unexpected properties \\['red'\\]"):
            read_scaffold_ply(variant("e.ply", extra="red"))
        with _raises(tmp_path / "f.ply", "no f_offset_"):
            read_scaffold_ply(variant("f.ply", keep=lambda n: not n.startswith("f_offset")))
        ints = np.zeros(2, dtype=[(n, "<i4" if n == "opacity" else "<f4") for n in names])
        write_ply(tmp_path / "g.ply", ints)
        with _raises(tmp_path / "g.ply", "'opacity' is not a float"):
            read_scaffold_ply(tmp_path / "g.ply")

    def test_inria_file_is_not_a_scaffold_file(self, tmp_path):
        write_inria_ply(tmp_path / "g.ply", _random_gaussians(4, 3))
        with _raises(tmp_path / "g.ply", "INRIA 3DGS PLY: `proxycodec render` and `eval` take it"):
            read_scaffold_ply(tmp_path / "g.ply")

    def test_truncated_scaffold_file(self, tmp_path):
        write_scaffold_ply(tmp_path / "s.ply", _random_scaffold(m=5))
        raw = (tmp_path / "s.ply").read_bytes()
        (tmp_path / "s.ply").write_bytes(raw[:-10])
        with _raises(tmp_path / "s.ply", "truncated"):
            read_scaffold_ply(tmp_path / "s.ply")

    def test_double_properties_are_read(self, tmp_path):
        s = _random_scaffold(m=3, k=2, f=2)
        names = scaffold_attribute_names(2, 2)
        arr = np.zeros(3, dtype=[(n, "<f8") for n in names])
        mat = s.attribute_matrix()
        for j, n in enumerate(names):
            arr[n] = mat[:, j]
        write_ply(tmp_path / "d.ply", arr)
        assert read_scaffold_ply(tmp_path / "d.ply") == s

    def test_shape_validation(self):
        with pytest.raises(ProxycodecError, match="offsets must have shape"):
            ScaffoldPly(np.zeros((2, 3)), np.zeros((2, 10, 2)), np.zeros((2, 32)), np.zeros((2, 6)))
        with pytest.raises(ProxycodecError, match="scalings must have shape"):
            ScaffoldPly(np.zeros((2, 3)), np.zeros((2, 10, 3)), np.zeros((2, 32)), np.zeros((2, 3)))
        with pytest.raises(ProxycodecError, match="write_scaffold_ply expects a ScaffoldPly"):
            write_scaffold_ply("/nonexistent/x.ply", object())  # type: ignore[arg-type]


# ============================================================================================== INRIA 3DGS
def _random_gaussians(n: int, degree: int, seed: int = 0, normals: bool = True) -> GaussianPly:
    rng = np.random.default_rng(seed)
    return GaussianPly(
        rng.normal(size=(n, 3)),
        rng.normal(size=(n, (degree + 1) ** 2, 3)),
        rng.normal(size=n),
        rng.normal(size=(n, 3)),
        rng.normal(size=(n, 4)),
        has_normals=normals,
    )


class TestInriaPly:
    def test_hand_built_file_channel_major_rest(self, tmp_path):
        n, deg = 2, 1
        names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [
            f"f_rest_{i}" for i in range(9)
        ]
        names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        assert names == inria_attribute_names(deg)
        rows = np.arange(n * len(names), dtype=np.float32).reshape(n, len(names))
        rows[:, 3:6] = 0
        raw = (
            "ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
            + "".join(f"property float {nm}\n" for nm in names)
            + "end_header\n"
        ).encode() + rows.tobytes()
        g = read_inria_ply(_write(tmp_path / "p.ply", raw))
        assert g.sh_degree == deg and g.n_gaussians == n
        col = {nm: j for j, nm in enumerate(names)}
        for c in range(3):
            np.testing.assert_array_equal(g.sh[:, 0, c], rows[:, col[f"f_dc_{c}"]])
            for j in range(3):  # f_rest_{c*3+j} is coefficient j+1 of channel c
                np.testing.assert_array_equal(g.sh[:, 1 + j, c], rows[:, col[f"f_rest_{c * 3 + j}"]])
        np.testing.assert_array_equal(g.quats, rows[:, -4:])
        np.testing.assert_array_equal(g.opacities, rows[:, col["opacity"]])
        write_inria_ply(tmp_path / "q.ply", g)
        assert (tmp_path / "q.ply").read_bytes() == raw

    @pytest.mark.parametrize("degree", [0, 1, 2, 3])
    @pytest.mark.parametrize("normals", [True, False])
    def test_round_trip(self, tmp_path, degree, normals):
        g = _random_gaussians(11, degree, seed=degree, normals=normals)
        write_inria_ply(tmp_path / "g.ply", g)
        back = read_inria_ply(tmp_path / "g.ply")
        assert back == g and back.sh_degree == degree and back.has_normals == normals
        assert read_ply_header(tmp_path / "g.ply").names == tuple(inria_attribute_names(degree, normals))
        n_rest = 3 * ((degree + 1) ** 2 - 1)
        assert sum(nm.startswith("f_rest_") for nm in read_ply_header(tmp_path / "g.ply").names) == n_rest

    def test_normals_written_as_zeros_by_default(self, tmp_path):
        g = _random_gaussians(3, 0)
        write_inria_ply(tmp_path / "g.ply", g)
        _, data = read_ply(tmp_path / "g.ply")
        for k in ("nx", "ny", "nz"):
            assert np.all(data[k] == 0)

    def test_infinite_opacity_logits_read_as_saturated(self, tmp_path):
        """splat-transform's SPZ -> PLY writes logit(1) = +inf for an alpha byte of 255: read as a finite logit whose
        sigmoid is exactly 1 (and -inf as one whose sigmoid is 0 to float32 precision); finite values, however large,
        and the other fields stay exact."""
        from proxycodec.formats.inria_ply import SATURATED_LOGIT

        g = _random_gaussians(4, 2)
        write_inria_ply(tmp_path / "g.ply", g)
        _, data = read_ply(tmp_path / "g.ply")
        data["opacity"][1], data["opacity"][3], data["opacity"][2] = np.inf, -np.inf, 44.0
        g.opacities[2] = 44.0
        write_ply(tmp_path / "inf.ply", data)
        got = read_inria_ply(tmp_path / "inf.ply")
        assert np.isfinite(got.opacities).all()
        assert got.opacities[1] == SATURATED_LOGIT and got.opacities[3] == -SATURATED_LOGIT
        sig = 1 / (1 + np.exp(-got.opacities.astype(np.float32)))
        assert sig[1] == np.float32(1.0) and sig[3] < 1e-12
        assert np.array_equal(got.opacities[[0, 2]], g.opacities[[0, 2]])
        assert np.array_equal(got.means, g.means) and np.array_equal(got.sh, g.sh)

    def test_errors(self, tmp_path):
        write_inria_ply(tmp_path / "g.ply", _random_gaussians(3, 1))
        _, data = read_ply(tmp_path / "g.ply")
        bad = data.copy()
        bad["opacity"][0] = np.nan
        write_ply(tmp_path / "nan.ply", bad)
        with _raises(tmp_path / "nan.ply", "'opacity'.*NaN"):
            read_inria_ply(tmp_path / "nan.ply")
        keep = [n for n in data.dtype.names if n != "f_rest_8"]
        sub = np.zeros(3, dtype=[(n, "<f4") for n in keep])
        for n in keep:
            sub[n] = data[n]
        write_ply(tmp_path / "rest.ply", sub)
        with _raises(tmp_path / "rest.ply", "8 f_rest_.*expected 0, 9, 24 or 45"):
            read_inria_ply(tmp_path / "rest.ply")
        write_scaffold_ply(tmp_path / "s.ply", _random_scaffold(2))
        with _raises(tmp_path / "s.ply", "Scaffold-GS anchor PLY: `proxycodec encode`"):
            read_inria_ply(tmp_path / "s.ply")
        with _raises(tmp_path / "missing.ply", "file not found"):
            read_inria_ply(tmp_path / "missing.ply")
        with pytest.raises(ProxycodecError, match="1, 4, 9 or 16"):
            GaussianPly(
                np.zeros((1, 3)), np.zeros((1, 2, 3)), np.zeros(1), np.zeros((1, 3)), np.zeros((1, 4))
            )

    def test_sh_dc_helpers(self):
        assert SH_C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)), abs=1e-16)
        rgb = np.array([0.0, 0.5, 1.0])
        np.testing.assert_allclose(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, atol=1e-12)
        assert rgb_to_sh_dc(0.5) == 0.0
        import torch

        t = torch.tensor([0.2, 0.9])
        torch.testing.assert_close(sh_dc_to_rgb(rgb_to_sh_dc(t)), t)
