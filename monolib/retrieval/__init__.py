"""Stage 4, the cells: the paper's GCN (`gcn`) and image baselines (`baselines`), both trained by one triplet
trainer (`training`), nearest-neighbour retrieval and recall/precision@k on the protocols (`evaluate`), the study's
grid of cells (`grid`) and one cell end to end (`cell`). Imports the stages before it and the shared tools only."""
