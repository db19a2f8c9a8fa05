"""balustrade.models."""
