"""balustrade.learn."""
