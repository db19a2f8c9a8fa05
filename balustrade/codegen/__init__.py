"""balustrade.codegen."""
