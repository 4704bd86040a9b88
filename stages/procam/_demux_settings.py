"""The demultiplexer's default settings (§5.2.2; :class:`selpath.stages.procam._demux_problem.DemuxProblem` and
:class:`selpath.stages.procam._demux_solver.DemuxADMM`), in a module without JAX: the stages that expose them as
settings (``demux_plane_to_ray``, ``demux_full``) give them as their defaults, so reading or validating a workflow
imports no solver. The solver's own class attributes (``DemuxADMM.DEFAULT_TOL``, …) are these values.

Why each is what it is, measured: docs/demux-settings.md."""

#: smoothness weight α of the thesis (§5.2.2), on images scaled to [0, 1]
DEFAULT_ALPHA = 0.01
#: sparsity weight β of the thesis (§5.2.2), on images scaled to [0, 1]
DEFAULT_BETA = 0.01
#: ADMM penalty ρ = rho_factor · λ_max(2G): 0.01 was the best of 0.003–0.3 on a Fig. 38-like sweep
DEFAULT_RHO_FACTOR = 0.01

#: projected accelerated gradient steps of the KKT bound's dual ascent (``_demux_certificate.kkt_gap``) in the
#: solver's final certificate: each costs one K × K product per pixel. Measured ad hoc in float64 on the solver's
#: float32 answers to ``benchmarks/demux_catalogue.py``'s thesis K = 128 case (the bound's median / p99): 0 steps
#: 3.0e-4 / 0.20, 10 steps 9.8e-5 / 1.0e-2, 20 steps 8.3e-5 / 7.4e-3, 50 steps 7.2e-5 / 5.1e-3, where the true
#: gap's median is 9.0e-5
DUAL_STEPS = 10

#: ADMM's relative primal and dual residual at which to stop [1]
TOL = 2e-3
#: ADMM iterations at most
MAX_ITER = 200
#: iterations between convergence checks
CHECK_EVERY = 5
#: ADMM iterations per polish round on the support found
POLISH_ITER = 5
#: polish rounds
POLISH_ROUNDS = 2
#: certified relative objective gap at which a pixel is converged [1]
GAP_TOL = 1e-4
#: certified relative gap above which the exact finish runs, and a pixel beyond it fails [1]
MAX_GAP = 1e-3
#: active-set rounds of the exact finish at most
FINISH_ROUNDS = 16
