"""Readers and writers of the file formats wreckmap exchanges with users and other tools."""
