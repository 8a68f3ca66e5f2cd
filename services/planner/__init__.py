"""The natural-language planner: words to a plan an LLM writes, checked by a dry run, refusals fed back."""
