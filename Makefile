# Thin aliases of dev.sh (which works without make too).
.PHONY: setup demo test lion-table
setup:
	bash dev.sh setup
demo:
	bash dev.sh demo
test:
	bash dev.sh test
lion-table: setup
	.venv/bin/python scripts/lion_table.py
