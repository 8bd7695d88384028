"""The neural-network engine (paper Sect. 3): networks, costs, training, committees, model files.

Independent of GalSim and click. Modules: :mod:`.network` (forward/backward passes),
:mod:`.costs` (MSE, MSB, MSWB with analytic derivatives), :mod:`.normalization`,
:mod:`.data` (cases x realizations), :mod:`.train` (BFGS with mini-batches, one member),
:mod:`.committee` (members as parallel work units, best half kept), :mod:`.model` (HDF5).
"""
