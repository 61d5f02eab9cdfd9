"""The paper's recipes, the demo, the speed-vs-accuracy sweep and the findings built from committed results."""
