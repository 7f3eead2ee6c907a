from benchmark.cli import console_main

console_main()
