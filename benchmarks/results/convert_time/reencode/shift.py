"""As run 2026-11-29 (paths of that machine). The 2400-s conversion's anchor scene with its positions as the shifted-grid conversion writes them (training is the
same: only the canonical -> world map of the positions changes, by float32 rounding)."""
import shutil, zlib
from dataclasses import replace
import numpy as np, torch
from proxycodec.formats.container import read_container, write_container
from proxycodec.formats.scaffold_ply import ScaffoldPly, read_scaffold_ply, write_scaffold_ply
from proxycodec.convert import CanonicalFrame
from proxycodec.model import SceneModel
src = "/work/runs/convtime/t2400/work/bonsai/converted_anchors"
dst = "/work/runs/reenc/shift/converted_anchors"
w = read_container(src + ".weights.pxc")
cf = w.meta["fit"]["canonical_frame"]
frame = CanonicalFrame(np.asarray(cf["center"], np.float64), float(cf["scale"]))
m = SceneModel.load(src + ".ply")
vox_w = m.scene.voxel_size
vox_c = vox_w / frame.scale
pos_w = m.scene.positions.double().numpy()
pos_c = ((pos_w - frame.center) / frame.scale)
ii = np.rint(pos_c / (vox_c / 16))  # the finest subdivision
pc32 = torch.from_numpy((ii * (vox_c / 16)).astype(np.float32))
# the canonical positions as training had them: f32(i * step) on the coarsest grid that holds them all
from proxycodec.sections import grid_positions
print("canonical on grid:", grid_positions(pc32.numpy(), vox_c) is not None)
new, shift = frame.positions_out(pc32, vox_c)
old_map = (pc32.double() * frame.scale + torch.from_numpy(frame.center)).float()
print("max |old file - old map|", float((old_map.double() - torch.from_numpy(pos_w)).abs().max()),
      "max |new - old file|", float((new.double() - torch.from_numpy(pos_w)).abs().max()), "voxel", vox_w, "shift", shift)
ply = read_scaffold_ply(src + ".ply")
write_scaffold_ply(dst + ".ply", replace(ply, positions=new.numpy()))
data = open(dst + ".ply", "rb").read()
meta = {**w.meta, "scene": {**w.meta["scene"], "grid_shift": shift}, "anchor_ply": {"bytes": len(data), "crc32": zlib.crc32(data)}}
write_container(dst + ".weights.pxc", meta, w.arrays, level=3)
print("wrote", dst)
