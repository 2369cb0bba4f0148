"""Built-in CoEx plugins: modalities, vehicle inputs and autonomy outputs; each registers through entry points."""
