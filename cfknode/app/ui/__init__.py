"""What a person sees: the live dashboard, its status, the flight summary and plots."""
