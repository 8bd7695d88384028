"""Constants of the training, import-free: the choices the declarations of
:mod:`megalut_cli.nn.options` offer and the code implements, and the iterations of each kind
of committee."""

#: scipy optimizers of the members (``bfgs``: BFGS, ``lbfgs``: L-BFGS-B).
OPTIMIZERS = ("bfgs", "lbfgs")
#: Arithmetic of the network passes during training.
PRECISIONS = ("float64", "float32")
#: How members start: N(0, 0.1), or near-identity on one feature.
INIT_SCHEMES = ("normal", "identity")
#: Costs a point estimator can be trained with (MSE only for comparison).
POINT_COSTS = ("msb", "mse")
#: The cost of the weight networks (paper Eq. 5).
WEIGHT_COST = "mswb"
#: Optimizer iterations per member of point and of weight committees, by default.
POINT_ITERATIONS = 1000
WEIGHT_ITERATIONS = 300
#: The paper's five input features (Sect. 5.3).
DEFAULT_FEATURES = ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4")
