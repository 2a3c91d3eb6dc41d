"""``skidbench evaluate``: fit every model on each terrain's Train split and score CV and LD."""
