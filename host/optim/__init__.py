"""The optimisers of the host loops: Adam (:mod:`~octcl.host.optim.adam`) and L-BFGS on the host
(:mod:`~octcl.host.optim.lbfgs`) and with its vectors on an OpenCL device
(:mod:`~octcl.host.optim.lbfgs_device`, ``kernels/lbfgs.cl``)."""
