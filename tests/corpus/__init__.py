"""Corpora of realistic inputs, each case with the answer it must give."""
