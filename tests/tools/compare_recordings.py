"""Compare two HDF5 recordings dataset by dataset: bit-for-bit equality, else the largest difference.
Used to check that a refactoring keeps the recordings of a run bit for bit:
  python tests/tools/compare_recordings.py OLD.h5 NEW.h5      (exit 1 when a dataset differs)"""
import sys
import h5py
import numpy as np
a, b = h5py.File(sys.argv[1], "r"), h5py.File(sys.argv[2], "r")
names = sorted(set(a) | set(b))
ok = True
for n in names:
    if n == "events":
        ea = [x.decode() if isinstance(x, bytes) else x for x in a["events/text"][()]]
        eb = [x.decode() if isinstance(x, bytes) else x for x in b["events/text"][()]]
        ta, tb = a["events/time_s"][()], b["events/time_s"][()]
        same = ea == eb and np.array_equal(ta, tb)
        print(f"events: {'identical' if same else 'DIFFER'} ({len(ea)} / {len(eb)})")
        if not same:
            print("  ", ea, eb); ok = False
        continue
    if n not in a or n not in b:
        print(f"{n}: only in {'first' if n in a else 'second'}"); ok = False; continue
    x, y = a[n][()], b[n][()]
    if x.shape != y.shape:
        print(f"{n}: shapes {x.shape} vs {y.shape}"); ok = False; continue
    same = np.array_equal(x, y, equal_nan=True)
    d = np.nanmax(np.abs(x - y)) if not same else 0.0
    print(f"{n}: {'bit-for-bit equal' if same else f'DIFFER, max |diff| {d:.3g}'} {x.shape}")
    ok &= same
    la, lb = a[n].attrs.get("labels"), b[n].attrs.get("labels")
    if la is not None and lb is not None and list(la) != list(lb):
        print(f"   labels differ: {list(la)[:3]}... vs {list(lb)[:3]}...")
print("ALL DATASETS EQUAL" if ok else "DIFFERENCES FOUND")
sys.exit(0 if ok else 1)
