from experiments.recovery.report import main

main()
