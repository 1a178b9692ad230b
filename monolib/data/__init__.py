"""Stage 1, the data: the Hypersim reader (`hypersim`), the rendered mini-Hypersim (`synth`), NYU40 labels
(`labels`), which test settings each protocol takes (`protocols`) and which frames a study uses (`selection`).
Imports only the shared tools (`monolib.params`, `io`, `paths`, ...)."""
