"""Stage 1, the data: the study's dataset opened or rendered and the stage's key (`dataset`), the Hypersim reader
(`hypersim`), the rendered mini-Hypersim (`synth`), NYU40 labels (`labels`), which test settings each protocol takes
(`protocols`) and which frames a study uses (`selection`). Imports only the shared tools (`monolib.params`, `io`,
`paths`, ...)."""
