"""msf-bench: CPU latency, throughput and accuracy benchmark for MSF-Net models and the runtime."""
