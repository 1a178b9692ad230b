"""Stage 3, scene graphs: one graph per frame from depth and semantics (`build`), or from published graph files
(`published`); `scenegraphs` builds and caches them per scenario under the stage's key; `fidelity` compares the
ground-truth graphs with real Hypersim's. Imports the data and perception stages and the shared tools only."""
