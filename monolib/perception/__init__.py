"""Stage 2, perception: depth (`depth`) and NYU40 semantics (`segmentation`) from one RGB image, on ImageNet
encoders (`imagenet`), with shipped weights (`weights`, `manifests`, `zoo`); `predictions` trains or loads,
evaluates and predicts every selected frame, under the stage's key. Imports the data stage and the shared tools
only."""
