"""Decoder fuzzing: a harness, its seeds, and tools to take ``.dftpc`` files apart."""
