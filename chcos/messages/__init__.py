"""messages - layer 5, the message manager of thesis section 6.1.2: moves messages on links
(tgetc/tputc), keeps command ownership (topen/tclose/teotsk/msgstat) and readies receivers.
"""
