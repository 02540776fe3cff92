"""motok.eval"""
