"""balustrade.problems."""
