# Thin aliases of dev.sh (which works without make too).
.PHONY: setup demo test lion-table vdb-env test-vdb bench scaling robustness robustness-quick
setup:
	bash dev.sh setup
demo:
	bash dev.sh demo
test:
	bash dev.sh test
lion-table: setup
	.venv/bin/python scripts/lion_table.py
vdb-env:
	bash dev.sh vdb-env
test-vdb:
	bash dev.sh test-vdb
bench: setup
	.venv/bin/python scripts/bench.py
scaling: setup
	.venv/bin/python scripts/scaling.py
robustness: setup
	.venv/bin/python scripts/robustness_study.py
robustness-quick: setup
	.venv/bin/python scripts/robustness_study.py --quick
