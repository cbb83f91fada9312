"""Nonlinear refinement of the joined map while submaps keep arriving (Gauss-Newton on eq. (7)).

:mod:`.online` is the refiner (pure numpy/scipy): it keeps every submap received so far, a
warm-started estimate of all their variables, and takes one Gauss-Newton step at a time.
:mod:`.worker` runs it in a process of its own and hands each refined map to a sink (the node's
publisher, or a queue back to the caller). :mod:`.race` is the benchmark against iSAM2.
"""
