"""The contract: every message that crosses a process boundary, and every key it travels on."""
