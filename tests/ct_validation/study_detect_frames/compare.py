"""Newly found shadows of AFTER.json against BEFORE.json (study.py outputs): errors and z per axis."""
import json, sys, numpy as np
b = json.load(open(sys.argv[1])); v = json.load(open(sys.argv[2]))
key = lambda s: (s["seed"], s["view"], s["sphere"])
seeds = {s["seed"] for s in v["shadows"]}
bk = {key(s): s for s in b["shadows"] if s["seed"] in seeds}
vk = {key(s): s for s in v["shadows"]}
new = [vk[k] for k in vk if k not in bk and vk[k]["vis"]]
lost = [bk[k] for k in bk if k not in vk]
print("new", len(new), "lost", len(lost))
z = np.array([np.array(s["err"]) / np.array(s["std"]) for s in new]).reshape(-1, 2)
e = np.array([s["err"] for s in new]).reshape(-1, 2)
for s, zz in zip(new, z):
    print(s["seed"], s["view"], s["sphere"], "err %+.4f %+.4f std %.4f %.4f z %+.1f %+.1f" % (*s["err"], *s["std"], *zz), "corner" if s["corner"] else "")
if len(new):
    print("z rms", np.sqrt((z**2).mean(0)), "err rms", np.sqrt((e**2).mean(0)))
# changed shadows among common
common = [k for k in bk if k in vk]
d = np.array([np.array(vk[k]["err"]) - np.array(bk[k]["err"]) for k in common])
print("common", len(common), "max change", np.abs(d).max() if len(d) else 0)
# all clear shadows z rms baseline
zb = np.array([np.array(s["err"]) / np.array(s["std"]) for s in b["shadows"] if s["vis"] and s["seed"] in seeds])
print("baseline clear z rms", np.sqrt((zb**2).mean(0)), "n", len(zb))
