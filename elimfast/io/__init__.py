"""Input and output: HDF5 (the only module importing h5py)."""
