"""The paper's method (Zou, Brenner, Sester, RA-L 2023, Section III), one module per step, in order.

=====================  =====================================================================
module                 step
=====================  =====================================================================
``step1_facades``      buildings; façade planes by RANSAC; the local frame by PCA; point
                       normals (Section III, IV.B)
``step2_layers``       the GMM of depth layers (eq. 3) and their facets on the plane (III.A)
``step3_training``     GP training points: what the layers do not explain (eqs. 7, 8; III.C)
``step4_gp_blocks``    local GPs in blocks: kernel (eq. 4), marginal likelihood, batched
                       Cholesky solves (III.B, III.D)
``step5_outliers``     the chi-squared outlier test (III.E)
``step6_surface``      one façade fitted (or updated) through steps 2-5 onto a surface raster:
                       :func:`fit_facade`, :func:`update_facade`
``step7_queries``      the surface at façade locations; answers for 3D points
``step8_occupancy``    occupancy probability of a voxel from the uncertain surface (IV.C)
=====================  =====================================================================

Every step takes arrays and plain parameters and returns arrays or the data types of
:mod:`uncertain_facade_map.datatypes`. The map of many buildings that grows with new points
(:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap`) calls them.
"""
