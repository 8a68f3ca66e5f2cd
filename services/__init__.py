"""tether's services: each a small package whose logic does not import zenoh."""
