"""How LLM agents reach the robot: generated tool schemas, the MCP server, feedback text for models."""
