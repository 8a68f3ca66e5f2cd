"""The resolver's reference corpus and its runner."""
