"""balustrade.dsl."""
