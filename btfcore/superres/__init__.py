"""Super-resolution of material BTFs (stage 11): the SR paper, D. den Brok, S. Merzbach,
M. Weinmann, R. Klein, "Per-image super-resolution for material BTFs", ICCP 2020.

* :mod:`btfcore.superres.espcn`: the per-image CNN (ESPCN with a skip connection and
  batch norm, SR paper §4.2, eqs. (5)-(6)), HDR input normalisation, batched inference;
* :mod:`btfcore.superres.training`: patch pairs and the network's training (SR paper §5.2.2);
* :mod:`btfcore.superres.scaling`: area down-sampling and bicubic up-sampling;
* :mod:`btfcore.superres.dong`: Dong et al.'s regularised up-sampling of eigentextures
  (SR paper §3.4, eqs. (3)-(4)), the baseline;
* :mod:`btfcore.superres.regions`: regions of interest at a finer pixel grid, rectified
  at a larger texture (SR paper §3.3-§4).

Pure numerics (numpy, OpenCV, torch); the modules are imported explicitly, this package
imports none of them.
"""
