"""Frames of kept ct_indep recordings to npz (for study.py). Usage: extract.py ROOT:SEED ... """
import os, sys, pathlib, numpy as np
FRAMES = os.environ.get("BGS_FRAMES", "/tmp/bgs/frames")
from ct_calib_nodes.io.mcap_io import iter_recording
from ct_calib_nodes.io.convert import array_from_image, stage_from_joint_state, stamp_ns
from ct_calib_nodes.io.ct_files import load_instrument

for root_seed in sys.argv[1:]:
    root, seed = root_seed.split(":")
    rec = pathlib.Path(root) / "recordings" / f"scan_{seed}"
    out = pathlib.Path(f"{FRAMES}/{seed}.npz")
    if out.exists():
        continue
    inst = load_instrument(rec / "ct_instrument.yaml")
    imgs, stg = {}, {}
    for m in iter_recording(rec / f"scan_{seed}.mcap"):
        if m.topic.endswith("ct/image") or "Image" in m.type_name:
            imgs[stamp_ns(m.msg.header.stamp)] = array_from_image(m.msg, (inst.detector.rows, inst.detector.cols))
        elif "JointState" in m.type_name:
            stg[stamp_ns(m.msg.header.stamp)] = stage_from_joint_state(m.msg)
    ts = sorted(set(imgs) & set(stg))
    encs = {imgs[t][1] for t in ts}
    assert len(encs) == 1, encs
    np.savez(out, images=np.stack([imgs[t][0] for t in ts]), encoding=encs.pop(), alpha=np.array([stg[t][0] for t in ts]),
             srd=np.array([stg[t][1] for t in ts]))
    print(seed, len(ts), flush=True)
