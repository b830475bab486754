from bench.cli import main

# The guard matters: render workers are spawned processes that re-import this module.
if __name__ == "__main__":
    main()
