"""Input and output: the HDF5 run and sweep files (the only package importing h5py).

safety.py: locks, disk space, atomic creation, SWMR crash recovery and repair helpers;
layout.py: the run group shared by run and sweep files; runfile.py: the run file's
writer and reader; sweepfile.py: the sweep file; hdf5.py: all of them under one name;
xarray_view.py: a Result as an xarray Dataset; xarray_tree.py: a file as an xarray DataTree.
"""
