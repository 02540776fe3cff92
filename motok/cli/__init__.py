"""motok.cli"""
