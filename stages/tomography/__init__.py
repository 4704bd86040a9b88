"""Chapter 4: optical tomography of diffuse-surface objects under the shortest-path model.

``acquire`` / ``simulate`` (captures) → ``calibrate`` (absorption, Eq. 3) → ``hull`` (silhouettes, visual hull)
→ ``paths`` (light-path alignment) → ``sinogram`` (binning, observed mask, coverage) → ``reconstruct`` (FBP,
constrained TV by ADMM); ``phantom``, ``evaluate`` and ``studies`` for simulated truths and Table 1; ``figures``.
"""
