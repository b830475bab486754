from bench.cli import entry

# The guard matters: render workers are spawned processes that re-import this module.
if __name__ == "__main__":
    entry()
