"""Input/output: HDF5 datasets, dataset generation, figures and animations, run outputs."""
