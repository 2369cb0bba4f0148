"""Decoders written from the text of ``spec/`` alone, run as other implementations would be."""
