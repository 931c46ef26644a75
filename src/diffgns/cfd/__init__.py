"""Cylinder-flow CFD ground truth: meshes (``mesh``), Taylor-Hood operators (``fem``), the
projection solver (``solver``), shedding analysis (``analysis``) and datasets (``dataset``,
``datagen``). See README "Cylinder-flow CFD"."""
