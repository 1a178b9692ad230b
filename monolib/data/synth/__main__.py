"""`python -m monolib.data.synth`: the render benchmark (`monolib.data.synth.dataset.benchmark`)."""
from monolib.data.synth.dataset import benchmark

benchmark()
