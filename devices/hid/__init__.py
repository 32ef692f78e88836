"""HID device kinds: descriptor-driven mice, pens and touch surfaces, and motion controllers."""
