"""Running a study: the stages in order and the grid of cell notebooks (`runner`), the cells copied from another
(`copies`), a notebook's papermill run (`notebooks`) on warm kernels (`kernels`), local worker processes or a Dask
cluster (`cluster`), and the grid's cost measured (`scaling`). The only wing that imports every stage."""
