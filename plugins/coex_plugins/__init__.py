"""Built-in CoEx plugins (modalities and tools); each sub-package registers through entry points."""
