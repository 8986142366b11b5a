# Thin aliases of dev.sh (which works without make too).
.PHONY: setup demo test lion-table bench scaling
setup:
	bash dev.sh setup
demo:
	bash dev.sh demo
test:
	bash dev.sh test
lion-table: setup
	.venv/bin/python scripts/lion_table.py
bench: setup
	.venv/bin/python scripts/bench.py
scaling: setup
	.venv/bin/python scripts/scaling.py
