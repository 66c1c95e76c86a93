"""The paper benchmark: the authors' simulation protocol (Table 1) and the controllers compared on it."""
