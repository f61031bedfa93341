"""The learned variance mask: its figure, its forms, pairs with scene change."""
