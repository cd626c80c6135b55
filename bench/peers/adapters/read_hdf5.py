"""Read datasets from HDF5 files (incl. MATLAB v7.3 .mat) into .npy, inside a throwaway
venv that has h5py (the project itself does not depend on h5py).

    python read_hdf5.py REQUESTS.json
REQUESTS.json: [{"path": file, "dataset": name, "out": .npy path}, ...]. Prints the
h5py version.
"""

import json
import sys

import h5py
import numpy as np

for req in json.loads(open(sys.argv[1]).read()):
    with h5py.File(req["path"], "r") as f:
        np.save(req["out"], np.asarray(f[req["dataset"]][()], dtype=float))
print(h5py.__version__)
