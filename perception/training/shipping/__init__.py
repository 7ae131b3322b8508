"""From checkpoints to shipped weights: the recipe's stages (`recipe_stages`), shipping with
manifest entries (`ship`) and test figures recorded there (`record`)."""
