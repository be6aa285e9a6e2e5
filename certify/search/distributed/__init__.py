"""Where chunks of work run: in this process or on a Dask cluster, with the problem
and the tensors as plain data in transit."""
