"""balustrade.backends."""
