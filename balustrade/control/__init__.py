"""balustrade.control."""
