// placeholder: kernels being written
