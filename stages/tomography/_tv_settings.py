"""The constrained TV reconstruction's default settings (Eq. 20, :class:`selpath.stages.tomography._admm.TVADMM`), in
a module without JAX: the stages that expose them as settings (``reconstruct_tv``, the studies) give them as their
defaults, and reading or validating a workflow then imports no solver."""

#: λ of Eq. 20 [absorption² per (1/length)·cell]
TV_WEIGHT = 1e-3
#: ADMM penalty relative to ‖MR‖² [1]
RHO = 0.1
#: relative primal and dual residual at which to stop [1]
TOL = 1e-3
#: iterations at most
MAX_ITER = 200
#: conjugate-gradient steps per σ-update (warm-started)
CG_STEPS = 3
